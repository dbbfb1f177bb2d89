"""The in-process reference trainer: batched envs and learner updates in one loop, one process.

This is the baseline the distributed runtime has to beat, and what the learning tests run. It talks to the
algorithm only through its public calls (act / observe / updates_for / can_update / update), exactly as the
learner process will, and to the env only through the batched interface, so the env is built by the caller
(``services``) and this module imports no environment code.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from convoy.actors.stepping import EnvStepper
from convoy.algos.algorithm import Algorithm, Progress, epsilon_at
from convoy.algos.checkpoint import BEST_CHECKPOINT, save_checkpoint
from convoy.envs.batched import BatchedEnv
from convoy.learner.runlog import Evaluator, RunLog, write_artefacts

from convoy.config import JobConfig


@dataclass
class TrainResult:
    """What a finished run reports; also written to ``summary.json``."""

    env_steps: int
    updates: int
    episodes: int
    wall_s: float
    env_steps_per_s: float
    updates_per_s: float
    final_return: float  # mean ε-greedy training return of the last 10 % of episodes
    eval_return: float  # greedy, on the fixed evaluation seeds
    eval_ci95: float
    random_return: float
    references: dict[str, list[float]] = field(default_factory=dict)  # policy → [mean, 95 % CI], same episodes
    best_eval_return: float = float("nan")  # the best point of the greedy curve (its policy is best.pt)
    best_eval_step: int = -1
    out_dir: str | None = None
    rows: list[dict[str, float]] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        d = dict(self.__dict__)
        d.pop("rows")
        return d


class Trainer:
    """Steps ``env`` with ``algo`` for ``job.steps`` env steps, logging, checkpointing and evaluating."""

    def __init__(
        self,
        job: JobConfig,
        env: BatchedEnv,
        algo: Algorithm,
        make_eval_env: Callable[[int], BatchedEnv] | None = None,
        out_dir: str | Path | None = None,
        progress: bool = True,
        on_row: Callable[[int], dict[str, float]] | None = None,
    ) -> None:
        """``on_row(env_steps)``: figures measured at every metric row and added to it (periodic evaluation)."""
        self.job, self.env, self.algo = job, env, algo
        self.on_row = on_row
        self.make_eval_env = make_eval_env
        self.out_dir = Path(out_dir) if out_dir is not None else None
        self.show_progress = progress
        self.cfg = job.algo_config()

    def run(self) -> TrainResult:
        job, env, algo = self.job, self.env, self.algo
        torch.manual_seed(job.seed)
        log = RunLog(job.steps, job.log_every, self.out_dir, self.show_progress)
        finished: list[float] = []
        env_steps = 0

        def save_best() -> None:  # best.pt, stamped with the step of the curve point that beat the best
            self._checkpoint(env_steps, len(finished), BEST_CHECKPOINT)

        evaluator = Evaluator(job, self.make_eval_env, save_best if self.out_dir else None)
        stepper = EnvStepper(env, algo, job.seed)
        owed = 0.0
        next_ckpt = job.checkpoint_every
        t0 = time.perf_counter()
        try:
            while env_steps < job.steps:
                algo.progress = Progress(env_steps, len(finished), job.steps, training=True)
                eps = epsilon_at(self.cfg, env_steps, job.steps)
                rets = stepper.step(eps)
                finished.extend(rets)
                log.episodes(rets)
                env_steps += env.num_envs
                if stepper.chunk_steps >= algo.chunk_len:
                    t_len = stepper.chunk_steps
                    algo.observe(stepper.take_chunk())
                    if algo.can_update():
                        owed += algo.updates_for(t_len * env.num_envs)
                    while owed >= 1.0 and algo.can_update():
                        log.update(algo.update())
                        owed -= 1.0
                extra: dict[str, float] = {}
                if log.row_due(env_steps):
                    if evaluator.due(env_steps, job.steps):
                        extra.update(evaluator.point(algo, env_steps))
                    if self.on_row:
                        extra.update(self.on_row(env_steps))
                log.maybe_row(env_steps, len(finished), algo.updates, eps, **extra)
                if self.out_dir and env_steps >= next_ckpt:
                    self._checkpoint(env_steps, len(finished))
                    next_ckpt += job.checkpoint_every
        finally:
            log.close()
        wall = time.perf_counter() - t0
        tail = finished[-max(1, len(finished) // 10) :] if finished else [float("nan")]
        try:
            final = evaluator.final(algo)
        finally:
            evaluator.close()
        result = TrainResult(
            env_steps=env_steps,
            updates=algo.updates,
            episodes=len(finished),
            wall_s=wall,
            env_steps_per_s=env_steps / wall,
            updates_per_s=algo.updates / wall,
            final_return=float(np.mean(tail)),
            **final,
            out_dir=str(self.out_dir) if self.out_dir else None,
            rows=log.rows,
        )
        if self.out_dir:
            self._checkpoint(env_steps, len(finished))
            write_artefacts(self.out_dir, result.as_dict(), log.rows, title=f"{job.algo} on {job.env}")
        return result

    def _checkpoint(self, env_steps: int, episodes: int, name: str = "checkpoint.pt") -> None:
        """The algorithm's state as ``name``: the last one, or ``best.pt`` for the best greedy-curve point."""
        assert self.out_dir is not None
        counters = {"env_steps": env_steps, "episodes": episodes, "updates": self.algo.updates}
        save_checkpoint(self.out_dir / name, self.algo, self.job, counters)
