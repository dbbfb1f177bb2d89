"""Composition of a training run: in this process (the job's env and agent handed to the in-process or population
trainer) or as learner and actor processes on this machine (``run_distributed``: a ``JobRunner``)."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

from convoy.config import JobConfig, job_config
from convoy.envs import make_batched
from convoy.envs.batched import BatchedEnv

if TYPE_CHECKING:  # torch and the trainer load only for in-process runs: a distributed parent never needs them
    from convoy.learner.inprocess import TrainResult


def make_env(job: JobConfig, num_envs: int | None = None) -> BatchedEnv:
    """The job's env as a batch of ``num_envs`` (default: the job's)."""
    return make_batched(job.env, job.num_envs if num_envs is None else num_envs, **job.env_params)


@contextmanager
def loaded_policy(path: str | Path, num_envs: int) -> Iterator[tuple[Any, BatchedEnv, JobConfig, dict[str, Any]]]:
    """``(algo, env, job, counters)`` of a saved policy, with ``num_envs`` envs of its job's env (closed after)."""
    from convoy.algos.checkpoint import load_checkpoint

    algo, job, counters = load_checkpoint(path, device="auto")
    env = make_env(job, num_envs)
    try:
        yield algo, env, job, counters
    finally:
        env.close()


def score_checkpoint(path: str | Path, episodes: int, seed: int | None = None) -> float:
    """A saved policy's mean greedy return over ``episodes`` episodes of ``seed`` (default: the held-out ones): the
    last policy and ``best.pt`` re-scored on episodes neither was chosen on."""
    from convoy.analysis.evaluation import HELD_OUT_SEED, SCORING_ENVS, evaluate_policy

    with loaded_policy(path, min(episodes, SCORING_ENVS)) as (algo, env, _, _):
        return evaluate_policy(algo, env, episodes, seed=HELD_OUT_SEED if seed is None else seed).mean


def run_inprocess(
    job: JobConfig, out_dir: str | Path | None = None, progress: bool = True, resume: bool = False
) -> TrainResult:
    """Train ``job`` in this process; writes metrics, curve, checkpoint and summary under ``out_dir``. ``resume``:
    go on from ``out_dir``'s checkpoint (weights, optimizer, counters, schedules, replay; the envs start new
    episodes) to ``job.steps``. One path: ``run_population`` of its one run."""
    out = Path(out_dir) if out_dir is not None else None
    (result,) = run_population([job], [out], progress, root=out, resume=resume)
    return result


def run_population(
    jobs: list[JobConfig],
    out_dirs: list[Path] | list[Path | None],
    progress: bool = True,
    root: Path | None = None,
    resume: bool = False,
) -> list[TrainResult]:
    """Train the jobs (one algorithm, one per seed; they may differ in the hyper-parameters a population lets runs
    differ in) as one population in this process (a single run: one job); run k writes ``out_dirs[k]`` as a single
    run of its seed would, the replay goes to ``root/replay.npz`` with each checkpoint; ``resume`` goes on from
    there."""
    from convoy.algos.agent import make_agent
    from convoy.algos.checkpoint import REPLAY_FILE
    from convoy.learner.core import print_line
    from convoy.learner.imitation import start_from_demonstrations
    from convoy.learner.population import PopulationTrainer
    from convoy.learner.resume import restore_population
    from convoy.learner.runtime import configure_learner

    job = jobs[0]
    configure_learner(job.torch_threads)
    env = make_env(job, job.num_envs * len(jobs))  # the agent's initial weights follow the seeds
    replay = root / REPLAY_FILE if root is not None else None
    try:
        configs = [j.algo_config() for j in jobs]  # the runs may differ in lr, γ, target period, ε schedule
        population = job_config(**{**job.model_dump(), "seeds": [j.seed for j in jobs]})  # one seed: a single run
        agent = make_agent(population, env.spec, run_configs=configs)
        counters = None
        if resume and replay is not None:
            dirs = [d for d in out_dirs if d is not None]
            counters = restore_population(agent, jobs, dirs, replay, strict=True)
        # minutes of DAgger when the job names a demonstrator: said even without a progress bar
        cloned_s = start_from_demonstrations(agent, population, out_dirs, print_line) if counters is None else None
        trainer = PopulationTrainer(jobs, env, agent, lambda n: make_env(job, n), out_dirs, progress=progress,
                                    replay=replay, counters=counters, cloned_s=cloned_s)  # fmt: skip
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
    job: JobConfig,
    out_dir: str | Path,
    progress: bool = True,
    job_id: str | None = None,
    stop_on_sigterm: bool = False,
) -> list[dict[str, Any]]:
    """Train ``job`` with ``job.runtime.actors`` actor processes and a learner process on this machine; each run's
    summary (one, or one per seed of a population), none when the job stopped early. ``stop_on_sigterm`` (the
    CLI): SIGTERM stops the job cleanly — children stopped, the learner checkpointed."""
    import signal

    from convoy.services.jobrunner import JobRunner

    runner = JobRunner(job_id or default_job_id(out_dir), job, out_dir, progress=progress)
    if stop_on_sigterm:
        signal.signal(signal.SIGTERM, lambda *_: runner.stop())
    summary = runner.run()
    return summary.get("runs", [summary]) if summary else []
