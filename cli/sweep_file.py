"""Sweep files: a sweep (``POST /sweeps``'s body) in TOML or JSON, optionally with named scales.

A file holds the sweep's fields at its top (``name``, ``actors``, ``threshold``, ``[base]``, ``[grid]``); a
``[scales.NAME]`` table overrides them for ``--scale NAME`` (its ``base`` merged key by key, its ``grid`` axes
replacing those of the same name; its ``note`` says how the scale departs from the paper; ``skip = "why"`` leaves the
file out at that scale; ``held_out_episodes`` is ``convoy reproduce``'s, not the sweep's). ``[figure]``
describes the paper's figure the file reproduces (``convoy reproduce``) and is not part of the sweep.
``extends = "OTHER.toml"`` (a path relative to the file) starts from that file's tables but its ``[figure]``, so a
figure's control groups share its base and scales instead of copying them.
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path
from typing import Any

from convoy.api.models import SweepSubmit
from convoy.api.sweeps import expand
from convoy.validation import ConfigError, build_config

NOT_SWEEP = ("scales", "figure")
SCALE_ONLY = ("grid", "note", "skip", "held_out_episodes")  # a scale's keys that are not the sweep's fields


def merged(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    """``base`` with ``over``'s keys, tables merged key by key (so a scale changes one hyper-parameter only)."""
    out = dict(base)
    for key, value in over.items():
        out[key] = merged(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


def read_file(path: str | Path, _seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    """The file's tables (over those of the file it ``extends``); a ConfigError naming the file and the line of a
    syntax error."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigError(str(path), f"cannot read the sweep file ({exc.strerror})") from None
    try:
        data = json.loads(text) if path.suffix == ".json" else tomllib.loads(text)
    except (tomllib.TOMLDecodeError, json.JSONDecodeError) as exc:
        kind = "JSON" if path.suffix == ".json" else "TOML"
        raise ConfigError(str(path), f"is not valid {kind}: {exc}") from None
    if not isinstance(data, dict):
        raise ConfigError(str(path), "must hold one object (the sweep)")
    parent = data.pop("extends", None)
    if parent is None:
        return data
    if not isinstance(parent, str) or not parent:
        raise ConfigError(f"{path}: extends", "names another sweep file, relative to this one")
    if path.resolve() in _seen:
        chain = " → ".join(p.name for p in (*_seen, path.resolve()))
        raise ConfigError(f"{path}: extends", f"files extend each other in a circle ({chain}); break it")
    base = read_file(path.parent / parent, (*_seen, path.resolve()))
    base.pop("figure", None)  # a figure's claims stay with the file that states them
    return merged(base, data)


def sweep_body(data: dict[str, Any], scale: str | None = None, where: str = "sweep") -> dict[str, Any]:
    """The ``POST /sweeps`` body of a file's tables at ``scale``, validated here so that a mistake is named before
    anything is sent; fields are named as in the file (``scales.quick.base.steps``)."""
    scales = data.get("scales") or {}
    body = {k: v for k, v in data.items() if k not in NOT_SWEEP}
    if scale is not None:
        if scale not in scales:
            have = ", ".join(scales) or "none"
            raise ConfigError("--scale", f"{where} has no scale {scale!r} (its scales: {have})")
        over = scales[scale]
        if over.get("skip"):
            raise ConfigError("--scale", f"{where} does not run at scale {scale!r}: {over['skip']}")
        body = merged(body, {k: v for k, v in over.items() if k not in SCALE_ONLY})
        body["grid"] = {**body.get("grid", {}), **over.get("grid", {})}
    try:
        expand(build_config(SweepSubmit, **body))  # every job of the grid, as the service will check it
    except ConfigError as exc:
        prefix = f"scales.{scale}." if scale is not None and _in_scale(exc.field, scales[scale]) else ""
        raise ConfigError(f"{prefix}{exc.field}", str(exc).split(": ", 1)[-1]) from None
    return body


def scale_table(data: dict[str, Any], scale: str) -> dict[str, Any]:
    """A file's ``[scales.SCALE]`` table, ``{}`` when it has none."""
    return (data.get("scales") or {}).get(scale) or {}


def skipped(data: dict[str, Any], scale: str) -> str:
    """Why a file does not run at ``scale`` (its ``[scales.SCALE] skip``), or ``""`` when it does."""
    return str(scale_table(data, scale).get("skip") or "")


def _in_scale(field: str, scale: dict[str, Any]) -> bool:
    node: Any = scale
    for part in field.split("."):
        if not isinstance(node, dict) or part not in node:
            return False
        node = node[part]
    return True


def load_sweep(path: str | Path, scale: str | None = None) -> dict[str, Any]:
    """The sweep body of the file at ``path`` (at ``scale``)."""
    return sweep_body(read_file(path), scale, where=str(path))
