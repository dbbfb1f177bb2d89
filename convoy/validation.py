"""Validation helpers shared by every env config: errors that name the field and its allowed range.

Env configs are pydantic models so that the CLI, the REST API and the worker processes validate
the same way. ``build_config`` turns pydantic's ValidationError into a ``ConfigError`` whose
message says which field is wrong, what was given, and what is allowed.
"""

from __future__ import annotations

from typing import Any, TypeVar

from annotated_types import Ge, Gt, Le, Lt
from pydantic import BaseModel, ValidationError

M = TypeVar("M", bound=BaseModel)


class ConfigError(ValueError):
    """An impossible configuration. ``field`` names the offending parameter."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(f"{field}: {message}")
        self.field, self.message = field, message


def flag_name(field: str) -> str:
    """The command line's flag for a config field: ``--num-envs`` for ``num_envs`` (every flag drawn from a model)."""
    return "--" + field.replace("_", "-")


def allowed_range(model: type[BaseModel], name: str) -> str | None:
    """Human-readable range of a numeric field, from its ``Field(ge=…, le=…)`` constraints."""
    head, _, rest = name.partition(".")
    info = model.model_fields.get(head)
    if info is None:
        return None
    if rest:  # a nested model's field: runtime.actors
        sub = info.annotation
        return allowed_range(sub, rest) if isinstance(sub, type) and issubclass(sub, BaseModel) else None
    low = high = None
    for m in info.metadata:
        if isinstance(m, Ge):
            low = f"{m.ge} ≤ "
        elif isinstance(m, Gt):
            low = f"{m.gt} < "
        elif isinstance(m, Le):
            high = f" ≤ {m.le}"
        elif isinstance(m, Lt):
            high = f" < {m.lt}"
    if low is None and high is None:
        return None
    return f"{low or ''}{name}{high or ''}"


def build_config(model: type[M], **values: Any) -> M:
    """Construct ``model`` from keyword values, raising ``ConfigError`` naming the first bad field."""
    unknown = sorted(set(values) - set(model.model_fields))
    if unknown:
        known = ", ".join(sorted(model.model_fields))
        raise ConfigError(unknown[0], f"unknown parameter for {model.__name__}; known parameters: {known}")
    try:
        return model(**values)
    except ValidationError as exc:
        err = exc.errors()[0]
        loc = [str(p) for p in err.get("loc", ())]
        field = ".".join(loc) if loc else model.__name__  # nested models: runtime.actors
        given = err.get("input")
        msg = err.get("msg", "invalid value")
        cause = err.get("ctx", {}).get("error")
        if isinstance(cause, ConfigError):  # raised by a cross-field model validator: it already explains
            raise cause from None
        rng = allowed_range(model, field)
        hint = f"; allowed range {rng}" if rng else ""
        raise ConfigError(field, f"{msg} (got {given!r}){hint}") from None
