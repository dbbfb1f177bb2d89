"""A reproduction's measured runs, kept in the repository: ``docs/reproduction/ledger/SCALE/FILE.json``.

Why: a real-budget figure takes days of compute, across sessions, on machines that need not keep ``runs/``. Each
run's scores — its greedy curve and final return, its last policy and ``best.pt`` re-scored on held-out episodes,
the references its job measured, Table 1's analysis of its checkpoint — are recorded as soon as its job completes.
A run the ledger holds is never trained again (the sweep leaves its grid point out), and the figure's groups are
summarised from the ledger alone, so committing the ledger keeps what a lost machine would otherwise take with it.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from convoy.api.lifecycle import JobRecord, JobState
from convoy.api.sweeps import summarize
from convoy.stats import mean_ci as seeds_summary

SET_ASIDE = "set-aside"  # beside a scale's ledgers: runs of a recipe the study no longer measures


def point_key(point: dict[str, Any]) -> str:
    """A grid point as the ledger names it: ``algo=idqn seed=3`` (axes sorted, so the grid's order does not
    matter)."""
    return " ".join(f"{k}={point[k]}" for k in sorted(point))


def request(spec: dict[str, Any]) -> dict[str, Any]:
    """The part of a sweep request that decides what its runs measure: all of it but the points left out, ``pack``,
    which only lays seeds out on processes (member k of a population is the single run of seed k:
    tests/test_population.py), so a slower machine may train smaller populations into the same ledger, and the
    ``compile`` switch, which captures the same update as one graph (equal to the eager one within 1e-5:
    tests/test_update_device.py), so a ledger's eager and compiled runs are one recipe's."""
    out = {k: v for k, v in spec.items() if k not in ("exclude", "pack")}
    if isinstance(out.get("base"), dict):
        out["base"] = _without_compile(out["base"], "algo_params")
    for name in list(out.get("algos") or {}):
        out["algos"] = _without_compile(out["algos"], name)
    return _without_compile(out, "algos")  # no algorithm's table left: as none


def recipe(spec: dict[str, Any]) -> dict[str, Any]:
    """What each run of sweep request ``spec`` measures: the request less its seed list, which says which runs there
    are, not what one of them measures, so a study may grow (or a diagnostic shrink) its seeds and keep the runs it
    holds."""
    out = request(spec)
    if isinstance(out.get("grid"), dict):
        out["grid"] = {k: v for k, v in out["grid"].items() if k != "seed"}
    return out


def preset_table(spec: dict[str, Any]) -> dict[str, Any] | None:
    """What the request's ``preset`` sets as this Convoy defines it, None without one: its rules, its parameters and
    (``resolved``) what each algorithm of the request takes of them. The request names a preset, not its settings,
    so a ledger keeps them beside it and sets aside the runs whose settings have changed since."""
    from convoy.config import PRESET_ALGO_PARAMS, algo_name, preset_params, preset_settings

    base = spec.get("base") or {}
    name = base.get("preset")
    if name not in PRESET_ALGO_PARAMS:
        return None
    env_params, algo_params = preset_settings(name)
    algos = (spec.get("grid") or {}).get("algo") or [base.get("algo", "ma-mesn")]
    resolved = {algo_name(str(a)): preset_params(name, str(a), bool(base.get("hierarchical")))[1] for a in algos}
    return json.loads(json.dumps({"env_params": env_params, "algo_params": algo_params, "resolved": resolved}))


def set_aside_path(path: Path, spec: dict[str, Any], preset: dict[str, Any] | None) -> Path:
    """Where the runs of ledger ``path`` measured under request ``spec`` and its preset's settings ``preset`` wait
    while the study measures another recipe: ``set-aside/FILE-HASH.json``, the hash of both."""
    key = json.dumps({"recipe": recipe(spec), "preset": preset}, sort_keys=True)
    return path.parent / SET_ASIDE / f"{path.stem}-{hashlib.sha256(key.encode()).hexdigest()[:8]}.json"


def measures(spec: dict[str, Any], preset: dict[str, Any] | None) -> dict[str, str] | None:
    """What each grid point of sweep request ``spec`` measures, by ``point_key``: its job's whole configuration with
    the preset resolved into it (so a preset renamed without changing what an algorithm takes of it changes
    nothing). None where that cannot be said today: the request no longer validates, or ``preset`` (the preset's
    settings as a ledger kept them) differs from the preset's definition now, which its jobs would resolve to; ""
    for a point whose algorithm took other settings of the preset then than it would now."""
    from convoy.api.models import SweepSubmit
    from convoy.api.sweeps import expand
    from convoy.validation import ConfigError, build_config

    now = preset_table(spec) or {}
    if preset is not None and any(preset.get(k) != now.get(k) for k in ("env_params", "algo_params")):
        return None
    changed = {a for a, params in (preset or {}).get("resolved", {}).items() if now["resolved"].get(a) != params}
    try:
        jobs = expand(build_config(SweepSubmit, **request(spec)))
    except ConfigError:
        return None
    return {point_key(j.point): "" if j.config.algo in changed else  # "": measured otherwise
            json.dumps(j.config.model_dump(mode="json", exclude={"preset"}), sort_keys=True) for j in jobs}  # fmt: skip


def _set_aside(path: Path, body: dict[str, Any]) -> None:
    """Add the runs of ledger ``body`` to the set-aside file ``path`` of the same recipe."""
    old = json.loads(path.read_text()) if path.is_file() else {}
    _write(path, {**body, "runs": {**old.get("runs", {}), **body["runs"]}})


def _write(path: Path, body: dict[str, Any]) -> None:
    """Write atomically: a kill mid-write leaves the previous file whole."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(body, indent=1, sort_keys=False) + "\n")
    os.replace(tmp, path)


def _without_compile(table: dict[str, Any], key: str) -> dict[str, Any]:
    """``table`` with its parameter table ``key`` less ``compile``; a table left empty dropped (it sets nothing,
    as an absent one)."""
    params = table.get(key)
    if not isinstance(params, dict):
        return table
    rest = {k: v for k, v in table.items() if k != key}
    params = {k: v for k, v in params.items() if k != "compile"}
    return {**rest, key: params} if params else rest


def training_change(run: dict[str, Any]) -> float | None:
    """A run's last greedy evaluation less its first: what training added to where the run started (for a run
    started from a demonstrator, what Q-learning added to its clone, one evaluation period in)."""
    curve = [float(r["eval_return"]) for r in run.get("rows", []) if r.get("eval_return") is not None]
    return curve[-1] - curve[0] if len(curve) >= 2 else None


def analysis_key(opts: dict[str, Any]) -> dict[str, Any]:
    """The settings an analysis depends on (a run analysed under others is analysed again where it can be)."""
    return {k: opts[k] for k in ("samples", "episodes", "seed", "num_envs") if k in opts}


@dataclass
class Ledger:
    """One experiment file's runs at one scale: the sweep request they were measured under and, per grid point,
    what its completed job measured."""

    path: Path
    spec: dict[str, Any]
    runs: dict[str, dict[str, Any]] = field(default_factory=dict)

    @classmethod
    def open(cls, path: Path, spec: dict[str, Any]) -> tuple[Ledger, str]:
        """The ledger at ``path`` for sweep request ``spec``, and a line saying what moved (or ""): a run whose job
        the request would now configure otherwise (its arm of the experiment file changed, or it left the grid)
        does not describe this study, so it moves to ``set-aside/`` beside the ledger, where the page still shows
        it; the other runs stay, and set-aside runs this request would configure as they were measured come back.
        """
        spec = request(spec)
        now = measures(spec, None) or {}  # no kept settings to compare: the preset as defined today
        data = json.loads(path.read_text()) if path.is_file() else {"spec": spec}
        runs = dict(data.get("runs", {}))
        before = measures(data["spec"], data.get("preset"))
        moved = {k: r for k, r in runs.items() if before is None or k not in now or before.get(k) != now[k]}
        ledger = cls(path, spec, {k: r for k, r in runs.items() if k not in moved})
        notes = []
        if moved:
            kept = set_aside_path(path, data["spec"], data.get("preset"))
            _set_aside(kept, {**data, "runs": moved})
            notes.append(f"{path}: {len(moved)} runs measured under another request set aside in {kept}")
        for archive in sorted((path.parent / SET_ASIDE).glob(f"{path.stem}-*.json")):
            old = json.loads(archive.read_text())
            then = measures(old["spec"], old.get("preset")) or {}
            back = {k: r for k, r in old["runs"].items() if k in now and then.get(k) == now[k] and k not in ledger.runs}
            if not back:
                continue
            ledger.runs.update(back)
            rest = {k: r for k, r in old["runs"].items() if k not in back}
            if rest:
                _write(archive, {**old, "runs": rest})
            else:
                archive.unlink()
            notes.append(f"{len(back)} runs of this request taken back from {archive}")
        if notes:
            ledger.save()  # the file names the recipe measured at once, before a run of it completes
        return ledger, "; ".join(notes)

    def has(self, point: dict[str, Any]) -> bool:
        return point_key(point) in self.runs

    def record(self, point: dict[str, Any], run: dict[str, Any]) -> None:
        """Keep ``run`` (what point ``point``'s completed job measured) and write the ledger at once."""
        self.runs[point_key(point)] = {"point": point, **run}
        self.save()

    def save(self) -> None:
        """Write atomically: a kill mid-write leaves the previous ledger whole."""
        body = {"spec": self.spec, "preset": preset_table(self.spec), "runs": dict(sorted(self.runs.items()))}
        _write(self.path, body)

    def groups(self, points: list[dict[str, Any]], others: dict[str, str]) -> list[dict[str, Any]]:
        """The sweep's groups summarised from the runs held (grid order), as the service summarises a sweep, with
        each group's held-out scores, references and training wall time; ``others``: the state of each point the
        ledger does not hold (failed, stopped, …), counted in its group's states."""
        held = [p for p in points if self.has(p)]
        reader = _Reader({point_key(p): self.runs[point_key(p)] for p in held})
        members = [{"id": point_key(p), "point": p} for p in held]
        members += [{"id": point_key(p), "point": p} for p in points if not self.has(p) and point_key(p) in others]
        reader.states = others
        threshold = self.spec.get("threshold")
        out = []
        for g in summarize(members, reader, threshold):
            runs = [self.runs[j] for j in g["jobs"] if j in self.runs]
            g["jobs"] = [r["job"] for r in runs] + [j for j in g["jobs"] if j not in self.runs]
            g["runs"] = runs
            g["references"] = next((r["references"] for r in runs if r.get("references")), {})
            walls: dict[str, float] = {}
            for r in runs:
                if r.get("wall_s") is not None:
                    walls[r["population"]] = max(walls.get(r["population"], 0.0), float(r["wall_s"]))
            g["wall_s"] = round(sum(walls.values()), 1) if walls else None
            # populations whose wall time may leave out a demonstration start (trained before runs said)
            g["clone_unknown"] = len({r["population"] for r in runs if (r.get("final") or {}).get("clone_s") is None})
            changes = [c for c in map(training_change, runs) if c is not None]
            if changes:
                g["change"] = seeds_summary(changes)
            scored = [r["held_out"] for r in runs if r.get("held_out")]
            if scored:
                g["held_out"] = {
                    "episodes": scored[0]["episodes"],
                    "seed": scored[0]["seed"],
                    **{k: seeds_summary([s[k] for s in scored if s.get(k) is not None]) for k in ("last", "best")},
                }
            out.append(g)
        return out


class _Reader:
    """The two reads ``summarize`` makes of a job store, answered from ledger runs."""

    def __init__(self, runs: dict[str, dict[str, Any]]) -> None:
        self.runs, self.states = runs, dict[str, str]()

    def get(self, job_id: str) -> JobRecord:
        run = self.runs.get(job_id)
        if run is None:  # a point the ledger does not hold: its state only
            return JobRecord(job_id, JobState(self.states[job_id]), {}, 1, 0.0, 0.0)
        progress = {"final": run["final"], "env_steps": run["env_steps"]}
        return JobRecord(job_id, JobState.completed, {"env": run["env"]}, 1, 0.0, 0.0, progress=progress)

    def metrics(
        self, job_id: str, since: int | None = None, names: list[str] | None = None, limit: int | None = None
    ) -> list[dict[str, Any]]:
        return list(self.runs[job_id]["rows"]) if job_id in self.runs else []
