"""Composition of a training run: build the job's env and agent, hand them to the in-process trainer."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from envs import make_batched
from envs.batched import BatchedEnv
from learner.agent import make_agent
from learner.inprocess import Trainer, TrainResult
from learner.runtime import configure_learner
from protocol.config import JobConfig


def make_env(job: JobConfig, num_envs: int | None = None) -> BatchedEnv:
    """The job's env as a batch of ``num_envs`` (default: the job's)."""
    return make_batched(job.env, job.num_envs if num_envs is None else num_envs, **job.env_params)


def run_inprocess(job: JobConfig, out_dir: str | Path | None = None, progress: bool = True) -> TrainResult:
    """Train ``job`` in this process; writes metrics, curve, checkpoint and summary under ``out_dir``."""
    configure_learner(job.torch_threads)
    torch.manual_seed(job.seed)
    env = make_env(job)
    try:
        agent = make_agent(job, env.spec)
        trainer = Trainer(job, env, agent, make_eval_env=lambda n: make_env(job, n), out_dir=out_dir, progress=progress)
        return trainer.run()
    finally:
        env.close()


def default_job_id(out_dir: str | Path) -> str:
    """A key-safe job id from the output directory's name plus a short random suffix (two runs never collide)."""
    import re
    import secrets

    stem = re.sub(r"[^A-Za-z0-9_.-]", "-", Path(out_dir).resolve().name).strip("-.") or "job"
    return f"{stem[:48]}-{secrets.token_hex(3)}"


def run_distributed(
    job: JobConfig, out_dir: str | Path, progress: bool = True, job_id: str | None = None
) -> dict[str, Any]:
    """Train ``job`` with ``job.runtime.actors`` actor processes and a learner process on this machine."""
    from services.jobrunner import JobRunner

    runner = JobRunner(job_id or default_job_id(out_dir), job, out_dir, progress=progress)
    return runner.run()
