"""What a training run does with experience, whoever steps the envs: one run's bookkeeping (``TrainingCore``).

The one trainer core (``learner/population.py``'s ``PopulationCore``, for R ≥ 1 runs) keeps one of these per run.
The in-process trainer feeds it the chunks of its own envs; the learner process (``learner/service.py``) the
chunks actors send over Zenoh. Both then share one rule for the updates a chunk is owed (``updates_for``: samples
per insert exactly), one metric row, one greedy curve with its best policy (``best.pt``), one checkpoint cadence
and one summary.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from convoy.algos.algorithm import Agent, Progress, epsilon_at
from convoy.algos.checkpoint import (
    BEST_CHECKPOINT,
    PREVIOUS_CHECKPOINT,
    REPLAY_FILE,
    drop_replay,
    save_checkpoint,
    save_replay,
)
from convoy.algos.updater import Figures, read_figures
from convoy.config import JobConfig
from convoy.envs.batched import BatchedEnv
from convoy.learner.runlog import Evaluator, RunLog, write_artefacts
from convoy.learner.trackers import Trackers
from convoy.transition import Transition

# Updates whose figures wait on the device before the trainer reads them, all at once: one host sync per READ_EVERY
# updates instead of one per update (on a GPU each sync stalls the queue of launched kernels), and a run whose loss
# stays non-finite fails at most READ_EVERY updates after its MAX_NONFINITE_IN_A_ROW-th (algos/algorithm.py). A
# metric row, and the end of the run, read whatever waits, so rows hold every update before them.
READ_EVERY = 64


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
    clone_s: float | None = None  # of wall_s, its demonstration start's (0: none; None: not known, an older resume)
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


class UpdateClock:
    """The updates a run owes the data it observed: ``updates_for`` per chunk (samples per insert exactly), the
    fraction carried over — one rule for a single run and a population. It also holds the updates' figures until
    they are read (``READ_EVERY``)."""

    def __init__(self, algo: Agent) -> None:
        self.algo, self.owed = algo, 0.0
        self.pending: list[Figures] = []

    def observe(self, chunk: Transition[np.ndarray], steps: int) -> None:
        """A chunk of ``steps`` env steps (per run) goes into the algorithm and is owed ``updates_for(steps)``."""
        self.algo.observe(chunk)
        if self.algo.can_update():
            self.owed += self.algo.updates_for(steps)

    def updates(self) -> Iterator[list[dict[str, float]]]:
        """Run the owed updates; yield the figures read meanwhile (every ``READ_EVERY`` updates), each update's one
        dict per run (a single run's: one)."""
        while self.owed >= 1.0 and self.algo.can_update():
            self.pending.append(self.algo.update())
            self.owed -= 1.0
            if len(self.pending) >= READ_EVERY:
                yield from self.read()

    def read(self) -> list[list[dict[str, float]]]:
        """The figures of every update not read yet, in one host read (``read_figures``: a run that stayed
        non-finite fails here)."""
        pending, self.pending = self.pending, []
        return read_figures(pending)


class TrainingCore:
    """Counts env steps and episodes, runs the owed updates, logs rows, evaluates, checkpoints and summarises.

    ``counters`` (a checkpoint's) resume a run where it stopped: the metric history is cut at its step and the
    best greedy return so far is kept. ``replay_bytes`` > 0 also writes the replay beside every ``checkpoint.pt``,
    so that a restarted learner or ``convoy train --resume`` does not start from an empty buffer.
    """

    def __init__(
        self,
        job: JobConfig,
        algo: Agent,
        out_dir: str | Path | None,
        make_eval_env: Callable[[int], BatchedEnv] | None,
        *,
        progress: bool = False,
        counters: dict[str, Any] | None = None,
        replay_bytes: int = 0,
        keep_previous: bool = False,
        say: Callable[[str], None] | None = None,
    ) -> None:
        """``say``: where the final evaluation tells what it does, a line as each part ends (by default the
        progress display's stdout when ``progress``, else nowhere)."""
        counters = counters or {}
        self.job, self.algo, self.cfg = job, algo, job.algo_config()
        if self.cfg.match_parameters is not None:  # the summary records the widths the network was built with
            self.cfg = self.cfg.model_copy(update={"hidden": getattr(algo, "cfg", self.cfg).hidden})
        self.out_dir = Path(out_dir) if out_dir is not None else None
        self.replay_bytes = replay_bytes
        self.say = say if say is not None else (print_line if progress else None)
        self.keep_previous = keep_previous  # a population's run: the checkpoint before stays, as PREVIOUS_CHECKPOINT
        self.saved_at = -1  # the env step of the last checkpoint.pt this core wrote
        self.env_steps = int(counters.get("env_steps", 0))
        self.episodes = int(counters.get("episodes", 0))
        self.returns: list[float] = []  # this process's finished episodes (their mean over agents)
        self.log = RunLog(
            job.steps,
            job.log_every,
            self.out_dir,
            progress,
            resume_at=self.env_steps if counters else None,
            first_step=self.env_steps,
            first_updates=algo.updates,
        )
        wall = counters.get("wall_s")  # the checkpoint's clock: a run resumed before its first row keeps its start's
        if isinstance(wall, int | float) and math.isfinite(wall) and wall > self.log.wall_before:
            self.log.wall_before = float(wall)
        # the seconds of its demonstration start in its clock: 0 for a fresh run until one is counted, unknown for a
        # run resumed from a checkpoint that did not say
        clone = counters.get("clone_s", None if counters else 0.0)
        self.clone_s = float(clone) if isinstance(clone, int | float) and math.isfinite(clone) and clone >= 0 else None
        self.evaluator = Evaluator(
            job,
            make_eval_env,
            save_best=(lambda: self.checkpoint(BEST_CHECKPOINT)) if self.out_dir else None,
            best=float(counters.get("best_eval_return", -math.inf)),
            first_step=self.env_steps,
        )
        self.clock = UpdateClock(algo)
        every = job.checkpoint_every
        self.next_checkpoint = (self.env_steps // every + 1) * every
        self.t0 = time.perf_counter()
        self.steps_at_start = self.env_steps
        self._closed = False
        self.trackers: Trackers | None = None
        if self.out_dir is not None:  # the run's resolved config: what `convoy train --resume` reads back
            self.out_dir.mkdir(parents=True, exist_ok=True)
            job.write(self.out_dir / "job.json")
            config = {**job.model_dump(mode="json", exclude={"runtime"}), "hyper_parameters": self.cfg.model_dump()}
            resume_at = self.env_steps if counters else None
            self.trackers = Trackers(self.out_dir, config, tuple(job.loggers), resume_at=resume_at)

    @property
    def done(self) -> bool:
        return self.env_steps >= self.job.steps

    @property
    def epsilon(self) -> float:
        return epsilon_at(self.cfg, self.env_steps, self.job.steps)

    def set_progress(self) -> None:
        """Tell the algorithm where training stands (SER's episode clock, CoDBC's β, hierarchical goals)."""
        self.algo.progress = Progress(self.env_steps, self.episodes, self.job.steps, training=True)

    def stepped(self, steps: int, returns: list[float]) -> None:
        """``steps`` env steps were taken and the episodes with ``returns`` ended."""
        self.env_steps += steps
        self.episodes += len(returns)
        self.returns.extend(returns)
        self.log.episodes(returns)

    def observe(self, chunk: Transition[np.ndarray], steps: int) -> None:
        """A chunk ``[T, B, …]`` of ``steps`` env steps goes into the algorithm; it is owed ``updates_for(steps)``."""
        self.clock.observe(chunk, steps)

    def update(self) -> None:
        """Run the updates observed data is owed (their figures reach the log as they are read)."""
        for figures in self.clock.updates():
            self.log.update(figures[0])

    def read_figures(self) -> None:
        """Every update's figures into the log, before a row or the summary counts them."""
        for figures in self.clock.read():
            self.log.update(figures[0])

    def row(self, extra: Callable[[int], dict[str, float]] | None = None) -> dict[str, Any] | None:
        """The metric row due at this step (with a greedy-curve point when one is due, and ``extra(env_steps)``),
        or None."""
        figures: dict[str, float] = {}
        if self.log.row_due(self.env_steps):
            self.read_figures()
            if self.evaluator.due(self.env_steps, self.job.steps):
                figures.update(self.evaluator.point(self.algo, self.env_steps))
            if extra is not None:
                figures.update(extra(self.env_steps))
        row = self.log.maybe_row(self.env_steps, self.episodes, self.algo.updates, self.epsilon, **figures)
        if row is not None and self.trackers is not None:
            self.trackers.row(row)
        return row

    @property
    def checkpoint_due(self) -> bool:
        return self.out_dir is not None and self.env_steps >= self.next_checkpoint

    def maybe_checkpoint(self) -> None:
        if self.checkpoint_due:
            self.checkpoint()
            while self.next_checkpoint <= self.env_steps:
                self.next_checkpoint += self.job.checkpoint_every

    def started_after(self, seconds: float) -> None:
        """Count ``seconds`` of work before the first step (a demonstration start's clone) in the run's wall clock."""
        self.log.wall_before += seconds
        self.clone_s = seconds

    def checkpoint(self, name: str = "checkpoint.pt", replay: bool = True) -> None:
        """The algorithm's state as ``name``: the last one, or ``best.pt`` for the best greedy-curve point (and the
        replay beside the last one, unless ``replay`` is off)."""
        assert self.out_dir is not None
        counters: dict[str, Any] = {
            "env_steps": self.env_steps,
            "episodes": self.episodes,
            "updates": self.algo.updates,
            "wall_s": self.log.wall_before + time.perf_counter() - self.log.t0,  # a resume's clock goes on from it
        }
        if self.clone_s is not None:
            counters["clone_s"] = self.clone_s
        if self.evaluator.best > -math.inf:
            counters["best_eval_return"] = self.evaluator.best  # a restart keeps best.pt unless it beats it
        if name == "checkpoint.pt" and self.replay_bytes and replay:  # replay first: a crash leaves no mismatch
            save_replay(self.out_dir / REPLAY_FILE, self.algo, self.env_steps, self.replay_bytes, self.say)
        path = self.out_dir / name
        if name == "checkpoint.pt" and self.keep_previous and path.is_file() and self.saved_at != self.env_steps:
            # a crash between two runs' checkpoints leaves them a step apart: the one before lets them resume together
            path.replace(self.out_dir / PREVIOUS_CHECKPOINT)
        save_checkpoint(path, self.algo, self.job, counters)
        if name == "checkpoint.pt":
            self.saved_at = self.env_steps

    def close(self) -> None:
        """The metric files (the trackers stay open for the summary: ``finish`` closes them)."""
        if not self._closed:
            self._closed = True
            self.log.close()

    def _close_trackers(self, summary: dict[str, Any] | None = None) -> None:
        if self.trackers is not None:
            if summary is not None:
                self.trackers.summary(summary)
            self.trackers.close()
            self.trackers = None

    def finish(self, title: str, end: float | None = None, **extra: Any) -> dict[str, Any]:
        """Close the log, checkpoint, evaluate the final policy beside the references, write ``summary.json`` and
        ``curve.png``; the summary. ``final_return`` is the mean ε-greedy return of the last 10 % of this
        process's episodes. ``end``: when training ended (``perf_counter``), if not now (a population's runs end
        together, then evaluate one after another)."""
        self.read_figures()
        self.close()
        if self.out_dir is not None:
            keep = self.job.runtime.keep_replay
            self.checkpoint(replay=keep)
            if not keep:
                drop_replay(self.out_dir / REPLAY_FILE)
        wall = (time.perf_counter() if end is None else end) - self.t0
        try:
            final = self.evaluator.final(self.algo, say=self.say)
        finally:
            self.evaluator.close()
        tail = self.returns[-max(1, len(self.returns) // 10) :] if self.returns else [math.nan]
        steps_here = self.env_steps - self.steps_at_start
        summary = {
            "algo": self.job.algo,
            "env": self.job.env,
            "seed": self.job.seed,
            "env_params": self.job.env_params,
            "hyper_parameters": self.cfg.model_dump(mode="json"),
            "env_steps": self.env_steps,
            "updates": self.algo.updates,
            "episodes": self.episodes,
            "wall_s": self.log.wall_before + wall,
            **({"clone_s": self.clone_s} if self.clone_s is not None else {}),
            "env_steps_per_s": steps_here / wall,
            "updates_per_s": (self.algo.updates - self.log.updates_at_start) / wall,
            "final_return": float(np.mean(tail)),
            **final,
            **extra,
        }
        if self.out_dir is not None:
            write_artefacts(self.out_dir, summary, self.log.rows, title=title)
        self._close_trackers(summary)
        return summary


def print_line(line: str) -> None:
    print(line, flush=True)
