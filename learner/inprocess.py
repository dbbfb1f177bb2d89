"""The in-process reference trainer: batched envs and learner updates in one loop, one process.

This is the baseline the distributed runtime has to beat, and what the learning tests run. It acts through the
actors' loop (``actors/stepping.py``) and feeds the trainer core the learner process feeds (``learner/core.py``), so
the algorithm sees the same calls either way; it reaches the env only through the batched interface
(``envs.batched``): the caller (``services.training``) builds the env, and this module imports no particular env.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from convoy.algos.algorithm import Agent
from convoy.algos.checkpoint import REPLAY_FILE
from convoy.config import JobConfig
from convoy.envs.batched import BatchedEnv
from convoy.learner.core import TrainResult
from convoy.learner.population import PopulationTrainer

__all__ = ["TrainResult", "Trainer"]


class Trainer:
    """Steps ``env`` with ``algo`` for ``job.steps`` env steps, logging, checkpointing and evaluating: the one
    training loop (``PopulationTrainer``) with a run of one, its folder ``out_dir`` and its replay beside it."""

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
        replay = self.out_dir / REPLAY_FILE if self.out_dir is not None else None
        (result,) = PopulationTrainer([self.job], self.env, self.algo, self.make_eval_env,
                                      [self.out_dir], self.show_progress, replay, [self.counters],
                                      self.on_row).run()  # fmt: skip
        return result
