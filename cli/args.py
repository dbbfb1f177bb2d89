"""What the commands share: ``add_command`` (a command's ``--help`` is its function's docstring), flags drawn from
the config models and the resource limits, ``KEY=VALUE`` pairs and env params."""

from __future__ import annotations

import argparse
import inspect
from collections.abc import Callable
from types import UnionType
from typing import Any, Literal, Union, get_args, get_origin

from pydantic import BaseModel

from convoy.config import JOB_FIELDS, ResourceLimits
from convoy.validation import ConfigError, flag_name

EXAMPLES = {"--set": "--set aggression=0.9", "--hp": "--hp lr=0.001"}


def parse_value(text: str) -> Any:
    """``KEY=VALUE`` values: int, float, true/false, none (None), comma lists (``64,64``), else the string itself."""
    if "," in text:
        return [parse_value(t.strip()) for t in text.split(",") if t.strip()]
    low = text.lower()
    if low in ("true", "false"):
        return low == "true"
    if low in ("none", "null"):
        return None
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return text


def parse_pairs(items: list[str] | None, flag: str) -> dict[str, Any]:
    """Repeated ``flag KEY=VALUE`` arguments as a dict; a malformed one is a ConfigError naming the flag."""
    out: dict[str, Any] = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(flag, f"expected KEY=VALUE (e.g. {EXAMPLES.get(flag, flag + ' key=1')}), got {item!r}")
        out[key.strip()] = parse_value(value.strip())
    return out


def add_command(sub: argparse._SubParsersAction, name: str, func: Callable[..., int], **kwargs: Any) -> Any:
    """A subcommand whose ``--help`` is ``func``'s docstring (its first line is the short help of the command list,
    the rest the description) and which runs ``func``."""
    short, _, long = inspect.cleandoc(func.__doc__ or name).partition("\n\n")
    short_help = (short[:1].lower() + short[1:].rstrip(".")).replace("%", "%%")  # argparse %-formats help
    p = sub.add_parser(name, help=short_help, description=long or short, **kwargs)
    p.set_defaults(func=func)
    return p


def add_model_flags(
    p: argparse.ArgumentParser, model: type[BaseModel], names: tuple[str, ...], flags: dict[str, str] | None = None
) -> None:
    """One flag per field of ``model`` in ``names`` (``--num-envs`` for ``num_envs``, or ``flags[name]``) with the
    field's type, description and default, so the CLI cannot drift from the config. Flags default to None (off
    for a switch): only what the user gives overrides the model's default or a config file."""
    for name in names:
        info = model.model_fields[name]
        flag = (flags or {}).get(name, flag_name(name))
        text = (info.description or name).rstrip(".")
        if info.annotation is bool:
            p.add_argument(flag, dest=name, action="store_const", const=True, help=f"{text} (default off)")
            continue
        if get_origin(info.annotation) is list:  # a list of ints (a population's seeds)
            p.add_argument(flag, dest=name, type=int, nargs="+", metavar="N", help=f"{text} (default none)")
            continue
        default = f"{info.default:,}" if isinstance(info.default, int) else info.default
        if default is None:  # an optional choice (``preset``): off unless given
            default = "none"
        optional = get_origin(info.annotation) in (Union, UnionType)  # ``X | None``: its choices are X's
        annotation = next(a for a in get_args(info.annotation) if a is not type(None)) if optional else info.annotation
        choices = get_args(annotation) if get_origin(annotation) is Literal else None
        kind: Callable[[str], Any] = int if info.annotation is int else float if info.annotation is float else str
        metavar = None if choices else "N" if kind in (int, float) else name.upper()
        p.add_argument(flag, dest=name, type=kind, choices=choices, metavar=metavar, help=f"{text} (default {default})")


def in_flag_words(exc: ConfigError, args: argparse.Namespace) -> ConfigError:
    """``exc`` naming the flag the user typed (``--steps``, ``--hp lr``) instead of the config field (``steps``)."""
    return ConfigError(flag_words(exc.field, args), exc.message)


def flag_words(field: str, args: argparse.Namespace) -> str:
    """The flag that gave a config ``field`` its value, as the user typed it (``--steps``, ``--agents``,
    ``--hp lr``, ``--set length``, ``--runtime chunk``); the field's own name when no flag gave it (a file's)."""
    if field.startswith("-"):  # already a flag
        return field
    aliases = {"n_agents": "agents", "n_adversaries": "adversaries", "runtime.actors": "actors"}
    flag = aliases.get(field, field)
    if (
        flag in (*JOB_FIELDS, "seeds", "device", "torch_threads", *aliases.values())
        and getattr(args, flag, None) is not None
    ):
        return flag_name(flag)
    head, _, sub = field.partition(".")
    for name, dest, key in (("--hp", "hp", field), ("--set", "set", field), ("--runtime", "runtime", sub)):
        pairs = getattr(args, dest, None)
        if key and (name != "--runtime" or head == "runtime") and key in parse_pairs(pairs, name):
            return f"{name} {key}"
    return field


def given(args: argparse.Namespace, names: tuple[str, ...]) -> dict[str, Any]:
    """The flags among ``names`` the user gave (those still at their ``None`` default left out)."""
    return {name: getattr(args, name) for name in names if getattr(args, name) is not None}


def env_params(args: argparse.Namespace, base: dict[str, Any] | None = None) -> dict[str, Any]:
    """Env parameters from ``--agents``, ``--adversaries`` and ``--set`` on top of ``base``."""
    params = dict(base or {})
    if args.agents is not None:
        params["n_agents"] = args.agents
    if args.adversaries is not None:
        params["n_adversaries"] = args.adversaries
    params.update(parse_pairs(args.set, "--set"))
    return params


def add_limit_flags(p: argparse.ArgumentParser) -> None:
    """``--max-layer-width`` etc.: one flag per ``ResourceLimits`` field, with its default."""
    for name, field in ResourceLimits.model_fields.items():
        p.add_argument(
            flag_name(name),
            type=int,
            default=field.default,
            metavar="N",
            help=f"largest job to accept: {field.description} (default: %(default)s)",
        )


def limits_from_args(args: argparse.Namespace) -> ResourceLimits:
    """The limits the flags of ``add_limit_flags`` set; a bad value is a ConfigError naming the flag."""
    values = {name: getattr(args, name) for name in ResourceLimits.model_fields}
    for name, value in values.items():
        if value < 1:
            raise ConfigError(flag_name(name), f"must be ≥ 1 (got {value})")
    return ResourceLimits(**values)
