"""Resuming a run from its folder: the last checkpoint's weights, optimizer, counters and replay into a fresh agent.

Two callers, two policies for a file that cannot be used. The learner process resumes after a crash or a stop on
its own, and an unusable file must not keep a job from running: it is set aside (``checkpoint.unreadable``) and the
job starts afresh (``strict=False``). ``convoy train --resume DIR`` is a user asking for that run: an unusable file
is an error naming it (``strict=True``). A checkpoint of another algorithm or env is an error either way.

A run resumes from its checkpoint (``DIR/checkpoint.pt``; a population's runs from theirs, ``DIR/seed-N/``, all of
one step) and the replay (``DIR/replay.npz``): one path, a single run is a population of one.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from convoy.algos.algorithm import Agent
from convoy.algos.checkpoint import (
    PREVIOUS_CHECKPOINT,
    REPLAY_FILE,
    CheckpointError,
    load_replay,
    read_checkpoint,
)
from convoy.config import ConfigError, JobConfig, job_config

log = logging.getLogger(__name__)


def _unusable(path: Path, why: str, strict: bool) -> None:
    """Say why ``path`` cannot be used: an error (strict), or set it aside and say the run starts afresh."""
    if strict:
        raise CheckpointError(f"checkpoint {path}: {why}; resume from another folder or train afresh")
    log.warning("checkpoint %s unusable (%s); starting from scratch", path, why)
    path.rename(path.with_suffix(".unreadable"))


def _payload(out_dir: Path, job: JobConfig, strict: bool, name: str = "checkpoint.pt") -> dict[str, Any] | None:
    path = out_dir / name
    if not path.is_file():
        if name != "checkpoint.pt":
            return None
        if strict:
            raise CheckpointError(f"{out_dir}: no checkpoint.pt to resume from; train the run first")
        return None
    try:
        payload = read_checkpoint(path)
        saved = job_config(**payload["job"])
    except (CheckpointError, ConfigError, KeyError, TypeError) as exc:
        _unusable(path, str(exc), strict)
        return None
    if (saved.algo, saved.env, saved.env_params) != (job.algo, job.env, job.env_params):
        raise CheckpointError(f"checkpoint {path}: belongs to {saved.algo} on {saved.env}; use another --out")
    return payload


def restore(algo: Agent, job: JobConfig, out_dir: str | Path, strict: bool = False) -> list[dict[str, Any]] | None:
    """Load the runs' last checkpoints (and the replay) into ``algo``: one dict of counters per run, each with
    ``replay_rows``, or None when there is nothing to resume — then ``algo`` may hold a partial load and must be
    built again."""
    out = Path(out_dir)
    return restore_population(algo, job.members(), job.member_dirs(out), out / REPLAY_FILE, strict)


def restore_population(
    algo: Agent, jobs: list[JobConfig], dirs: list[Path], replay: Path, strict: bool = False
) -> list[dict[str, Any]] | None:
    """Run k's checkpoint (``dirs[k]``, job ``jobs[k]``) into run k of ``algo`` and the population's replay from
    ``replay``; the runs' counters, or None unless every run has a checkpoint of one step (its last, or the one
    before it when a crash came between two runs' writes)."""
    # each run's last checkpoint and the one before: a crash between two runs' writes leaves them a step apart
    names = ("checkpoint.pt", PREVIOUS_CHECKPOINT)
    options = [[(p, d / name) for name in names if (p := _payload(d, job, strict, name))]
               for d, job in zip(dirs, jobs, strict=True)]  # fmt: skip
    if all(not o for o in options):
        return None
    by_step = [{int(p["counters"].get("env_steps", -1)): (p, path) for p, path in o} for o in options]
    common = set.intersection(*(set(b) for b in by_step))
    if not common:
        why = "the population's runs have no checkpoints of one step"
        if strict:
            raise CheckpointError(f"{replay.parent}: {why}; train afresh")
        log.warning("%s; starting afresh", why)
        return None
    step = max(common)
    payloads = [b[step][0] for b in by_step]
    for k, payload in enumerate(payloads):
        try:
            algo.load_member_state(k, payload["state"])
        except Exception as exc:  # the networks differ (other sizes): as unusable as a corrupt file
            _unusable(by_step[k][step][1], f"does not match the job's networks ({exc})", strict)
            return None
    rows = load_replay(replay, algo, step)
    demos = getattr(algo, "demos", None)
    if demos is not None and not len(demos):  # the margin would be off from here on, silently
        raise CheckpointError(f"{replay}: no demonstrations beside the checkpoint at {step:,} env steps, which "
                              "demo_margin needs (the replay file is missing or was over runtime.replay_checkpoint_mb)"
                              "; train afresh, or with a larger --runtime replay_checkpoint_mb=N")  # fmt: skip
    return [{**p["counters"], "replay_rows": rows} for p in payloads]
