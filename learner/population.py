"""Training R runs of one algorithm, one per seed, stepped and updated together (a single run: R = 1).

The agent holds every run's weights, optimizer state, replay and random streams on a leading run axis
(``NetworkAgent(seed=[s_0, …])``); the env holds R·B envs, run k's seeded as the single run of ``s_k`` seeds its
own (``actors/stepping.py``). One act serves all runs, one update steps all of them. Everything a run writes — its
metric rows, greedy curve, ``best.pt``, ``checkpoint.pt``, ``summary.json`` — comes from its own
:class:`~convoy.learner.core.TrainingCore` fed with that run's episodes and figures, over ``agent.member(k)``: the
run as a single-run agent, refreshed from the population before a row or checkpoint needs it. So each run's folder
is what a single run of its seed writes, and ``convoy eval``/``analyze`` read it unchanged.

:class:`PopulationCore` is that bookkeeping, shared by the in-process :class:`PopulationTrainer` (the one training
loop: ``learner/inprocess.py``'s ``Trainer`` is it for one run) and the learner process (``learner/service.py``),
which takes the same chunks ``[T, R, B, …]`` from actors over Zenoh.

Why: a run's cost is its learner update and the Python around acting (the env steps millions of agent-steps per
second); one process pays the acting, the env loop, start-up and evaluation set-up once for R runs, and on a GPU one
batched update of R runs costs about what one run's does. On a CPU the batched update costs what R updates cost
(``benchmarks/population.py``).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from convoy.actors.stepping import EnvStepper
from convoy.algos.algorithm import Agent, Progress
from convoy.algos.checkpoint import drop_replay, save_replay
from convoy.config import JobConfig
from convoy.envs.batched import BatchedEnv
from convoy.learner.core import TrainingCore, TrainResult, UpdateClock, print_line
from convoy.transition import Transition


class PopulationCore:
    """One :class:`TrainingCore` per run over one population agent: counts, rows, curves, checkpoints and summaries
    per run; one rule for the updates the population owes (every run inserts the same number of transitions, so
    every run owes the same updates) and one update for all runs."""

    def __init__(
        self,
        jobs: list[JobConfig],
        algo: Agent,
        out_dirs: list[Path] | list[Path | None] | None,
        make_eval_env: Callable[[int], BatchedEnv] | None,
        *,
        progress: bool = False,
        counters: list[dict[str, Any]] | list[dict[str, Any] | None] | None = None,
        replay: tuple[Path, int] | None = None,
        say: Callable[[str], None] | None = None,
    ) -> None:
        """``jobs[k]`` is run k's job (its seed ``algo.seeds[k]``); ``out_dirs[k]`` its folder; ``counters[k]``
        its checkpoint's counters when the population resumes; ``replay`` = (file, max bytes): the population's
        replay is written there before each checkpoint, as ``TrainingCore`` writes a single run's; ``say``: where
        each run's final evaluation tells what it does, its lines headed by the run's seed (by default stdout
        when ``progress``)."""
        if algo.runs != len(jobs) or [j.seed for j in jobs] != list(algo.seeds):
            raise ValueError("jobs: one job per run of the population, with the run's seed")
        self.jobs, self.algo = jobs, algo
        dirs = out_dirs or [None] * len(jobs)
        say = self.say = say if say is not None else (print_line if progress else None)
        several = len(jobs) > 1  # runs whose checkpoints are written one after another, whose lines need a head
        self.cores = [
            TrainingCore(
                job,
                algo.member(k),
                out,
                make_eval_env,
                progress=progress and k == 0,
                counters=c,
                keep_previous=several,
                say=_headed(say, f"seed {job.seed}: ") if say and several else say,
            )
            for k, (job, out, c) in enumerate(zip(jobs, dirs, counters or [None] * len(jobs), strict=True))
        ]
        self.clock = UpdateClock(algo)
        self.replay = replay

    @property
    def done(self) -> bool:
        return self.cores[0].done

    @property
    def env_steps(self) -> int:
        """Env steps of each run (they step together)."""
        return self.cores[0].env_steps

    @property
    def episodes(self) -> np.ndarray:
        """Episodes each run has finished."""
        return np.array([core.episodes for core in self.cores])

    @property
    def epsilon(self) -> np.ndarray:
        """Each run's exploration rate (runs may have their own schedules)."""
        return np.array([core.epsilon for core in self.cores])

    def set_progress(self) -> None:
        for core in self.cores:
            core.set_progress()
        self.algo.progress = Progress(self.env_steps, self.episodes, self.jobs[0].steps, training=True)

    def stepped(self, steps: int, returns: list[float], runs: np.ndarray) -> None:
        """Each run took ``steps`` env steps; the episodes with ``returns`` ended, ``runs[i]`` the run of the i-th."""
        for k, core in enumerate(self.cores):
            core.stepped(steps, [r for r, run in zip(returns, runs, strict=True) if run == k])

    def observe(self, chunk: Transition[np.ndarray], steps: int) -> None:
        """A chunk ``[T, R, B, …]`` of ``steps`` env steps per run; every run is owed ``updates_for(steps)``."""
        self.clock.observe(chunk, steps)

    def update(self) -> None:
        self._log(self.clock.updates())

    def _log(self, read: Iterable[list[dict[str, float]]]) -> None:
        for figures in read:  # one batched update: each run's figures to its own log
            for core, run_figures in zip(self.cores, figures, strict=True):
                core.log.update(run_figures)

    def row(self, extra: Callable[[int], dict[str, float]] | None = None) -> list[dict[str, Any]]:
        """The metric rows due at this step, one per run (all runs' fall due together), or none."""
        if any(core.log.row_due(core.env_steps) for core in self.cores):
            self._log(self.clock.read())  # the updates' figures not read yet, before a row counts them
        rows = []
        for k, core in enumerate(self.cores):
            if core.log.row_due(core.env_steps) or core.checkpoint_due:
                self.algo.member(k)  # the run's current state into its single-run view
            row = core.row(extra)
            if row is not None:
                rows.append(row)
        return rows

    def maybe_checkpoint(self) -> None:
        if self.cores[0].checkpoint_due:
            self._save_replay()
        for core in self.cores:  # row() refreshed each member whose checkpoint is due
            core.maybe_checkpoint()

    def _save_replay(self) -> None:
        """The population's replay, before its runs' checkpoints (a crash between leaves no mismatched pair)."""
        if self.replay is not None:
            save_replay(self.replay[0], self.algo, self.env_steps, self.replay[1], self.say)

    def started_after(self, seconds: float) -> None:
        """Count ``seconds`` of work before the first step (a demonstration start's clone) in each run's wall
        clock: the time a run took is what it cost, its start included."""
        for core in self.cores:
            core.started_after(seconds)

    def checkpoint(self) -> None:
        self._save_replay()
        for k, core in enumerate(self.cores):
            if core.out_dir is not None:
                self.algo.member(k)
                core.checkpoint()

    def close(self) -> None:
        for core in self.cores:
            core.close()

    def finish(self, title: Callable[[JobConfig], str], **extra: Any) -> list[dict[str, Any]]:
        """Each run's summary (``TrainingCore.finish`` over its member), in run order; training time ends now for
        all runs, though they are evaluated one after another."""
        end = time.perf_counter()
        self._log(self.clock.read())
        if self.replay is not None and self.jobs[0].runtime.keep_replay:
            self._save_replay()  # beside the runs' last checkpoints, when asked
        elif self.replay is not None:
            drop_replay(self.replay[0])  # a completed population needs its replay no more
        summaries = []
        for k, (core, job) in enumerate(zip(self.cores, self.jobs, strict=True)):
            self.algo.member(k)
            summaries.append(core.finish(title(job), end=end, **extra))
        return summaries


def _headed(say: Callable[[str], None], head: str) -> Callable[[str], None]:
    return lambda line: say(head + line)


def mean_row(rows: list[dict[str, Any]]) -> dict[str, float]:
    """A population's metric rows as one: each figure's mean over the runs that report it (what a supervisor
    shows for the whole job; each run's own rows are in its folder)."""
    keys = {k for row in rows for k in row}
    return {k: float(np.mean([row[k] for row in rows if k in row])) for k in sorted(keys)}


class PopulationTrainer:
    """Steps ``env`` (R × ``job.num_envs`` envs) with the population ``algo`` until every run has ``job.steps``: the
    one in-process training loop, for R ≥ 1 runs."""

    def __init__(
        self,
        jobs: list[JobConfig],
        env: BatchedEnv,
        algo: Agent,
        make_eval_env: Callable[[int], BatchedEnv] | None = None,
        out_dirs: list[Path] | list[Path | None] | None = None,
        progress: bool = True,
        replay: Path | None = None,
        counters: list[dict[str, Any]] | list[dict[str, Any] | None] | None = None,
        on_row: Callable[[int], dict[str, float]] | None = None,
        cloned_s: float | None = None,
    ) -> None:
        """``replay``: where the population's replay goes with each checkpoint; ``counters``: the runs'
        checkpoints' when ``algo`` resumes from them (``learner/resume.py``); ``on_row(env_steps)``: figures
        measured at every metric row and added to it (periodic evaluation); ``cloned_s``: the seconds of a
        demonstration start's clone, checkpointed before the first step (minutes of work a stop should not lose)
        and counted in each run's wall clock."""
        self.jobs, self.env, self.algo = jobs, env, algo
        self.make_eval_env = make_eval_env
        self.out_dirs = out_dirs
        self.show_progress = progress
        self.replay, self.counters = replay, counters
        self.on_row = on_row
        self.cloned_s = cloned_s

    def run(self) -> list[TrainResult]:
        algo, env = self.algo, self.env
        torch.manual_seed(self.jobs[0].seed)
        per_run_envs = env.num_envs // len(self.jobs)
        replay = (self.replay, self.jobs[0].runtime.replay_checkpoint_mb << 20) if self.replay else None
        core = PopulationCore(self.jobs, algo, self.out_dirs, self.make_eval_env, progress=self.show_progress,
                              counters=self.counters, replay=replay)  # fmt: skip
        stepper = EnvStepper(env, algo, seed=self.jobs[0].seed)
        try:
            if self.cloned_s is not None:
                core.started_after(self.cloned_s)
                core.checkpoint()
            while not core.done:
                core.set_progress()
                returns = stepper.step(core.epsilon)
                core.stepped(per_run_envs, returns, stepper.ended_runs)
                if stepper.chunk_steps >= algo.chunk_len:
                    steps = stepper.chunk_steps * per_run_envs
                    core.observe(stepper.take_chunk(), steps)
                    core.update()
                core.row(self.on_row)
                core.maybe_checkpoint()
        finally:
            core.close()
        seed = len(self.jobs) > 1  # a population's runs say their seed in their titles
        summaries = core.finish(lambda job: f"{job.algo} on {job.env}" + (f", seed {job.seed}" if seed else ""))
        dirs = self.out_dirs or [None] * len(self.jobs)
        return [
            TrainResult(**s, out_dir=str(out) if out else None, rows=c.log.rows)
            for s, out, c in zip(summaries, dirs, core.cores, strict=True)
        ]
