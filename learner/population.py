"""Population training in one process: R runs of one algorithm, one per seed, stepped and updated together.

The agent holds every run's weights, optimizer state, replay and random streams on a leading run axis
(``NetworkAgent(seed=[s_0, …])``); the env holds R·B envs, run k's seeded as the single run of ``s_k`` seeds its
own (``actors/stepping.py``). One act serves all runs, one update steps all of them. Everything a run writes — its
metric rows, greedy curve, ``best.pt``, ``checkpoint.pt``, ``summary.json`` — comes from its own
:class:`~convoy.learner.core.TrainingCore` fed with that run's episodes and figures, over ``agent.member(k)``: the
run as a single-run agent, refreshed from the population before a row or checkpoint needs it. So each run's folder
is what a single run of its seed writes, and ``convoy eval``/``analyze`` read it unchanged.

Why: a run's cost is its learner update and the Python around acting (the env steps millions of agent-steps per
second); one process pays the acting, the env loop, start-up and evaluation set-up once for R runs, and on a GPU one
batched update of R runs costs about what one run's does. On a CPU the batched update costs what R updates cost
(``benchmarks/population.py``).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from convoy.actors.stepping import EnvStepper
from convoy.algos.algorithm import NetworkAgent, Progress
from convoy.config import JobConfig
from convoy.envs.batched import BatchedEnv
from convoy.learner.core import TrainingCore
from convoy.learner.inprocess import TrainResult


class PopulationTrainer:
    """Steps ``env`` (R × ``job.num_envs`` envs) with the population ``algo`` until every run has ``job.steps``."""

    def __init__(
        self,
        jobs: list[JobConfig],
        env: BatchedEnv,
        algo: NetworkAgent,
        make_eval_env: Callable[[int], BatchedEnv] | None = None,
        out_dirs: list[Path] | None = None,
        progress: bool = True,
    ) -> None:
        """``jobs[k]`` is run k's job (its seed ``algo.seeds[k]``); ``out_dirs[k]`` its folder."""
        if algo.runs != len(jobs) or [j.seed for j in jobs] != list(algo.seeds):
            raise ValueError("jobs: one job per run of the population, with the run's seed")
        self.jobs, self.env, self.algo = jobs, env, algo
        self.make_eval_env = make_eval_env
        self.out_dirs = out_dirs or [None] * len(jobs)
        self.show_progress = progress

    def run(self) -> list[TrainResult]:
        algo, env, runs = self.algo, self.env, len(self.jobs)
        per_run_envs = env.num_envs // runs
        cores = [
            TrainingCore(job, algo.member(k), out, self.make_eval_env, progress=self.show_progress and k == 0)
            for k, (job, out) in enumerate(zip(self.jobs, self.out_dirs, strict=True))
        ]
        stepper = EnvStepper(env, algo, seed=self.jobs[0].seed)
        owed = 0.0  # every run owes the same updates: they insert the same number of transitions
        try:
            while not cores[0].done:
                for core in cores:
                    core.set_progress()
                episodes = np.array([core.episodes for core in cores])
                algo.progress = Progress(cores[0].env_steps, episodes, self.jobs[0].steps, training=True)
                returns = np.asarray(stepper.step(np.array([core.epsilon for core in cores])))
                for k, core in enumerate(cores):
                    core.stepped(per_run_envs, returns[stepper.ended_runs == k].tolist())
                if stepper.chunk_steps >= algo.chunk_len:
                    steps = stepper.chunk_steps * per_run_envs
                    algo.observe(stepper.take_chunk())
                    if algo.can_update():
                        owed += algo.updates_for(steps)
                    while owed >= 1.0 and algo.can_update():
                        for core, figures in zip(cores, algo.update(), strict=True):  # type: ignore[arg-type]
                            core.log.update(figures)
                        owed -= 1.0
                for k, core in enumerate(cores):
                    if core.log.row_due(core.env_steps) or core.checkpoint_due:
                        algo.member(k)  # the run's current state into its single-run view
                    core.row()
                    core.maybe_checkpoint()
        finally:
            for core in cores:
                core.close()
        end = time.perf_counter()
        results = []
        for k, (core, job) in enumerate(zip(cores, self.jobs, strict=True)):
            algo.member(k)
            summary = core.finish(f"{job.algo} on {job.env}, seed {job.seed}", end=end)
            out = self.out_dirs[k]
            results.append(TrainResult(**summary, out_dir=str(out) if out else None, rows=core.log.rows))
        return results
