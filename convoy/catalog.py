"""What can be trained: every environment and algorithm with its parameters (default, range, meaning) and the
defaults each env sets — one source for ``GET /envs``, ``GET /algos``, ``convoy env list --params`` and
``convoy algos``, read from the pydantic models themselves so that it cannot drift from what the config accepts."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel

from convoy.config import ALGORITHMS, ENV_DEFAULTS, AlgoConfig, env_defaults
from convoy.validation import allowed_range


def parameters(model: type[BaseModel]) -> dict[str, dict[str, Any]]:
    """Each field of ``model``: its default, allowed range (or None) and description."""
    out = {}
    for name, info in model.model_fields.items():
        default = info.get_default(call_default_factory=True)
        out[name] = {
            "default": list(default) if isinstance(default, tuple) else default,
            "range": allowed_range(model, name),
            "description": info.description or "",
        }
    return out


def envs() -> dict[str, dict[str, Any]]:
    """Every environment: what it is and its parameters (``env_params``, ``--set KEY=VALUE``)."""
    from convoy.envs.registry import ENVS

    return {name: {"summary": entry.summary, "params": parameters(entry.config())} for name, entry in ENVS.items()}


def algos() -> dict[str, dict[str, Any]]:
    """Every algorithm: what it is, its hyper-parameters (``algo_params``, ``--hp KEY=VALUE``; the common ones and
    its own) and the values each env sets where the job sets nothing."""
    out = {}
    for name, model in ((n, a.config) for n, a in ALGORITHMS.items()):
        own = [k for k in model.model_fields if k not in AlgoConfig.model_fields]
        per_env = {env: env_defaults(name, env) for env in ENV_DEFAULTS}
        out[name] = {"summary": ALGORITHMS[name].summary, "params": parameters(model), "own": own,
                     "env_defaults": {env: {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}
                                      for env, d in per_env.items()}}  # fmt: skip
    return out


def return_bounds(env: str) -> tuple[float, float] | None:
    """The returns env ``env`` allows, where its rules bound them (None: unbounded, or an unknown env): what a
    plot's CI band is clipped to."""
    from convoy.envs.registry import return_bounds as bounds  # the envs load on first use

    return bounds(env)
