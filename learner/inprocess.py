"""The in-process reference trainer: batched envs and learner updates in one loop, one process.

This is the baseline the distributed runtime has to beat, and what the learning tests run. It acts through the
actors' loop (``actors/stepping.py``) and feeds the trainer core the learner process feeds (``learner/core.py``), so
the algorithm sees the same calls either way; it reaches the env only through the batched interface
(``envs.batched``): the caller (``services.training``) builds the env, and this module imports no particular env.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from convoy.actors.stepping import EnvStepper
from convoy.algos.algorithm import Agent
from convoy.config import JobConfig
from convoy.envs.batched import BatchedEnv
from convoy.learner.core import TrainingCore


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
    algo: str = ""
    env: str = ""
    seed: int = 0
    env_params: dict[str, Any] = field(default_factory=dict)
    hyper_parameters: dict[str, Any] = field(default_factory=dict)  # the algorithm's resolved config
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
        algo: Agent,
        make_eval_env: Callable[[int], BatchedEnv] | None = None,
        out_dir: str | Path | None = None,
        progress: bool = True,
        on_row: Callable[[int], dict[str, float]] | None = None,
        counters: dict[str, Any] | None = None,
    ) -> None:
        """``on_row(env_steps)``: figures measured at every metric row and added to it (periodic evaluation);
        ``counters``: a checkpoint's, when ``algo`` resumes from it (``learner/resume.py``)."""
        self.job, self.env, self.algo = job, env, algo
        self.counters = counters
        self.on_row = on_row
        self.make_eval_env = make_eval_env
        self.out_dir = Path(out_dir) if out_dir is not None else None
        self.show_progress = progress

    def run(self) -> TrainResult:
        job, env, algo = self.job, self.env, self.algo
        torch.manual_seed(job.seed)
        core = TrainingCore(job, algo, self.out_dir, self.make_eval_env, progress=self.show_progress,
                            counters=self.counters, replay_bytes=job.runtime.replay_checkpoint_mb << 20)  # fmt: skip
        stepper = EnvStepper(env, algo, job.seed)
        try:
            while not core.done:
                core.set_progress()
                returns = stepper.step(core.epsilon)
                core.stepped(env.num_envs, returns)
                if stepper.chunk_steps >= algo.chunk_len:
                    steps = stepper.chunk_steps * env.num_envs
                    core.observe(stepper.take_chunk(), steps)
                    core.update()
                core.row(self.on_row)
                core.maybe_checkpoint()
        finally:
            core.close()  # the metric files, whichever way the loop ends
        summary = core.finish(f"{job.algo} on {job.env}")
        return TrainResult(**summary, out_dir=str(self.out_dir) if self.out_dir else None, rows=core.log.rows)
