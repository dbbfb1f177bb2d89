"""Sweeps: a grid of jobs (``expand``) and what their greedy-evaluation curves say together (``summarize``).

A sweep is a base job and a grid of axis values; each combination is one ordinary job of the service (queued,
scaled, stopped, resumed, reattached after a restart like any other). Jobs whose grid points differ only in
``seed`` form a *group*; the summary reports, per group, the mean and 95 % Student-t interval over seeds of the
greedy curve at common env-step points, of the final greedy return, and of the env steps and seconds each seed took
to reach a threshold return.
"""

from __future__ import annotations

import copy
import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from convoy.api.lifecycle import ACTIVE_STATES, JobReader, JobRecord, JobState, SweepRecord, UnknownJob
from convoy.api.models import GRID_TABLES, JobSubmit, SweepMember, SweepSubmit, SweepView
from convoy.catalog import return_bounds
from convoy.config import ConfigError, JobConfig, algo_name
from convoy.stats import curve_area, iqm_ci, mean_curve
from convoy.stats import mean_ci as _mean_ci
from convoy.validation import build_config


class RunReader(Protocol):
    """The reads a summary makes: a job and its metric rows (the job store, or a reproduction's ledger)."""

    def get(self, job_id: str) -> JobRecord: ...
    def metrics(
        self, job_id: str, since: int | None = None, names: list[str] | None = None, limit: int | None = None
    ) -> list[dict[str, Any]]: ...


@dataclass(frozen=True)
class SweepJob:
    """One grid point of a sweep and the job it runs."""

    point: dict[str, Any]
    config: JobConfig


def group_name(point: dict[str, Any]) -> str:
    """The group a grid point belongs to: its values but the seed, e.g. ``algo=idqn env_params.n_agents=4``."""
    return " ".join(f"{k}={v}" for k, v in point.items() if k != "seed") or "all"


def _canonical(algo: Any) -> str | None:
    try:
        return algo_name(str(algo))
    except ConfigError:
        return None  # the job's own validation names it


def expand(spec: SweepSubmit) -> list[SweepJob]:
    """Every job of the grid but the excluded points, validated; seeds outermost, so that each group's first seed
    runs first."""
    axes = sorted(spec.grid, key=lambda axis: axis != "seed")
    left_out = [sorted(point.items(), key=repr) for point in spec.exclude]
    jobs = []
    for values in itertools.product(*(spec.grid[axis] for axis in axes)):
        point = dict(zip(axes, values, strict=True))
        if sorted(point.items(), key=repr) in left_out:
            continue
        body = copy.deepcopy(spec.base)
        algo = _canonical(point.get("algo", body.get("algo", JobConfig.model_fields["algo"].default)))
        own = spec.algos.get(algo) if algo else None
        if own:  # this algorithm's own hyper-parameters, under the grid's
            body["algo_params"] = {**body.get("algo_params", {}), **own}
        for axis, value in point.items():
            table, _, key = axis.partition(".")
            if key:
                body.setdefault(table, {})
                if not isinstance(body[table], dict):
                    raise ConfigError(f"base.{table}", f"must be an object to vary {axis}")
                body[table][key] = value
            else:
                body[axis] = value
        try:
            config = build_config(JobSubmit, **body, actors=spec.actors).job_config()
        except ConfigError as exc:
            where = next((t for t in GRID_TABLES if isinstance(body.get(t), dict) and exc.field in body[t]), None)
            qualified = f"{where}.{exc.field}" if where else exc.field  # an algorithm's or env's own parameter
            varied = next((a for a in point if qualified == a or qualified.startswith(f"{a}.")), None)
            field = f"grid.{varied}" if varied else f"base.{qualified}"
            if not varied and own and where == "algo_params" and exc.field in own:
                field = f"algos.{point.get('algo', body.get('algo'))}.{exc.field}"
            problem = str(exc).split(": ", 1)[-1]
            raise ConfigError(field, f"{problem} (in the job {point})") from None
        jobs.append(SweepJob(point, config))
    return jobs


def population(configs: list[JobConfig]) -> JobConfig:
    """Jobs that differ only in seed as one population job (``seeds``): one learner trains them all at once."""
    return build_config(JobConfig, **{**configs[0].model_dump(), "seeds": [c.seed for c in configs]})


def packs(jobs: list[SweepJob], most: int, fits: Callable[[JobConfig], bool]) -> list[list[int]]:
    """The sweep's jobs as process groups (indices into ``jobs``, each pack in grid order of its first job): each
    group's seeds in populations of at most ``most`` runs — fewer while ``fits`` refuses the population (the
    service's limits on envs and weights count every run) — and every other job alone (a group of one seed,
    hierarchical DQN over DIAL)."""
    groups: dict[str, list[int]] = {}
    for i, job in enumerate(jobs):
        groups.setdefault(group_name(job.point), []).append(i)
    out: list[list[int]] = []
    for members in groups.values():
        first = jobs[members[0]].config
        size = 1 if first.hierarchical and first.algo == "dial" else min(most, len(members))
        while size > 1 and not fits(population([jobs[i].config for i in members[:size]])):
            size -= 1
        out += [members[i : i + size] for i in range(0, len(members), size)]
    return sorted(out, key=lambda pack: pack[0])


def sweep_state(states: dict[str, int]) -> str:
    """A sweep's state from how many of its jobs are in each state: running while one is queued or runs, then
    failed if one failed, stopped if one stopped, else completed."""
    if any(s.value in states for s in ACTIVE_STATES):
        return "running"
    return "failed" if states.get("failed") else "stopped" if states.get("stopped") else "completed"


def busy_seconds(spans: list[tuple[float, float]]) -> float:
    """How long at least one of the spans ran: their union's length, so a sweep stopped overnight and resumed
    counts only the time its jobs ran."""
    total, reach = 0.0, -math.inf
    for start, end in sorted(spans):
        if end > reach:
            total += end - max(start, reach)
            reach = end
    return total


def sweep_view(sweep: SweepRecord, reader: JobReader) -> SweepView:
    """The sweep's jobs with their states and progress, and the sweep's state from theirs."""
    members, done, asked, spans = [], 0, 0, []
    for member in sweep.jobs:
        try:
            rec = reader.get(member["id"])
        except UnknownJob:
            members.append(SweepMember(id=member["id"], point=member["point"], group=group_name(member["point"]),
                                       state="deleted"))  # fmt: skip
            continue
        steps, env_steps = int(rec.config.get("steps", 0)), int(rec.progress.get("env_steps", 0) or 0)
        if rec.progress.get("started_at") and rec.state != JobState.queued:  # a queued one's last run ended long ago
            spans.append((float(rec.progress["started_at"]), float(rec.updated_at)))
        done, asked = done + min(env_steps, steps), asked + steps
        demo = {k: rec.progress.get(k) for k in ("demo_round", "demo_rounds")} if env_steps == 0 else {}
        members.append(SweepMember(id=rec.id, point=member["point"], group=group_name(member["point"]),
                                   state=rec.state.value, env_steps=env_steps, steps=steps, **demo))  # fmt: skip
    states: dict[str, int] = {}
    for m in members:
        states[m.state] = states.get(m.state, 0) + 1
    state = sweep_state(states)
    return SweepView(id=sweep.id, state=state, created_at=sweep.created_at, jobs=members, states=states,
                     fraction=done / asked if asked else 0.0, started_at=min((a for a, _ in spans), default=None),
                     ended_at=max((b for _, b in spans), default=None) if state != "running" else None,
                     busy_s=busy_seconds(spans), spans=spans, spec=sweep.spec)  # fmt: skip


def greedy_curve(rows: list[dict[str, Any]], final: dict[str, Any] | None, end_step: int) -> tuple[np.ndarray, ...]:
    """A job's greedy curve: (env steps, return, wall seconds) of its evaluation rows, then its final evaluation."""
    points = [
        (int(r["env_steps"]), float(r["eval_return"]), float(r.get("wall_s", math.nan)))
        for r in rows
        if isinstance(r.get("eval_return"), int | float) and math.isfinite(r["eval_return"])
    ]
    last = final.get("eval_return") if final else None
    if isinstance(last, int | float) and math.isfinite(last) and (not points or end_step > points[-1][0]):
        wall = float(rows[-1].get("wall_s", math.nan)) if rows else math.nan
        points.append((end_step, float(last), wall))
    if not points:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros(0)
    steps, values, walls = zip(*points, strict=True)
    return np.array(steps, np.int64), np.array(values), np.array(walls)


def summarize_group(
    name: str, members: list[tuple[str, dict[str, Any]]], reader: RunReader, threshold: float | None
) -> dict[str, Any]:
    """One group: its jobs' states, the mean greedy curve ± CI at common steps (and ``bounds``, the returns its env
    allows, where the rules bound them), the final return (mean ± t-CI and interquartile mean with a bootstrap CI),
    the area under each completed job's greedy curve, the threshold."""
    states: dict[str, int] = {}
    curves, finals, areas, reached_steps, reached_wall, jobs = [], [], [], [], [], []
    bounds: tuple[float, float] | None = None
    for job_id, _ in members:
        try:
            rec = reader.get(job_id)
        except UnknownJob:
            continue  # deleted: the summary is of the jobs that remain
        jobs.append(job_id)
        bounds = return_bounds(str(rec.config.get("env", ""))) or bounds
        states[rec.state.value] = states.get(rec.state.value, 0) + 1
        final = rec.progress.get("final") if rec.state == JobState.completed else None
        rows = reader.metrics(job_id, names=["eval_return", "wall_s"])
        steps, values, wall = greedy_curve(rows, final, int(rec.progress.get("env_steps", 0) or 0))
        if len(steps):
            curves.append((steps, values))
        if final and isinstance(final.get("eval_return"), int | float) and math.isfinite(final["eval_return"]):
            finals.append(float(final["eval_return"]))
            areas.append(curve_area(steps, values))
        if threshold is not None and len(steps):
            hit = np.flatnonzero(values >= threshold)
            if len(hit):
                reached_steps.append(float(steps[hit[0]]))
                reached_wall.append(float(wall[hit[0]]))
    out: dict[str, Any] = {
        "group": name,
        "point": {k: v for k, v in members[0][1].items() if k != "seed"} if members else {},
        "jobs": jobs,
        "states": states,
        "curve": mean_curve(curves),
        "bounds": list(bounds) if bounds else None,  # the returns the env allows: a plot's band stays within them
        "final": _mean_ci(finals),
        "iqm": iqm_ci(finals),
        "auc": _mean_ci([a for a in areas if a is not None]),
    }
    if threshold is not None:
        out["threshold"] = {
            "value": threshold,
            "reached": len(reached_steps),
            "of": len(jobs),
            "env_steps": _mean_ci(reached_steps),
            "wall_s": _mean_ci([w for w in reached_wall if math.isfinite(w)]),
        }
    return out


def summarize(members: list[dict[str, Any]], reader: RunReader, threshold: float | None) -> list[dict[str, Any]]:
    """Every group of a sweep's jobs (``members``: ``{"id", "point"}`` in grid order), in order of appearance."""
    groups: dict[str, list[tuple[str, dict[str, Any]]]] = {}
    for member in members:
        groups.setdefault(group_name(member["point"]), []).append((member["id"], member["point"]))
    return [summarize_group(name, jobs, reader, threshold) for name, jobs in groups.items()]
