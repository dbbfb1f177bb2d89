"""What every training loop reports, in one place: metric rows, the progress display, the final evaluation and the
run's artefacts (``metrics.jsonl/csv``, ``summary.json``, ``curve.png``).

The in-process trainer and the distributed learner both log through :class:`RunLog`, so a row means the same in
both and the distributed runtime can be compared with its baseline column for column.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, cast

import numpy as np

from convoy.algos.listening import HearsMessages
from convoy.analysis.evaluation import evaluate, evaluate_random, listening, listening_for
from convoy.config import MessageSource
from convoy.envs.batched import BatchedEnv
from convoy.learner.metrics import MetricsWriter, plot_curves
from convoy.stats import ci95_half


class RunLog:
    """Accumulates returns and losses between rows; ``maybe_row`` emits a row every ``log_every`` env steps."""

    def __init__(
        self,
        total_steps: int,
        log_every: int,
        out_dir: str | Path | None = None,
        progress: bool = True,
        resume_at: int | None = None,
        first_step: int = 0,
        first_updates: int = 0,
    ) -> None:
        self.total, self.log_every = total_steps, log_every
        self.writer = MetricsWriter(out_dir, resume_at=resume_at) if out_dir is not None else None
        self.rows: list[dict[str, Any]] = list(self.writer.rows) if self.writer else []
        self.window: list[float] = []
        self.losses: list[float] = []
        self.skipped_updates = 0  # since the run (or this resume) began
        self.extra: dict[str, list[float]] = {}  # an algorithm's own update figures (memory accuracy, …)
        self.next_row = (first_step // log_every + 1) * log_every
        self.t0 = self.t_row = time.perf_counter()
        self.steps_at_row, self.updates_at_row = first_step, first_updates
        self.updates_at_start = first_updates
        self.wall_before = float(self.rows[-1].get("wall_s", 0.0)) if self.rows else 0.0
        self.bar = ProgressDisplay(total_steps, progress)

    def episodes(self, returns: list[float]) -> None:
        self.window.extend(returns)

    def loss(self, value: float) -> None:
        self.losses.append(value)

    def update(self, stats: dict[str, float]) -> None:
        """One update's figures: the TD loss, and whatever else the algorithm reports (averaged per row)."""
        if not math.isfinite(stats["loss"]):  # a skipped update (non-finite loss): counted, kept out of the mean
            self.skipped_updates += 1
            return
        self.losses.append(stats["loss"])
        for key, value in stats.items():
            if key not in ("loss", "grad_norm"):
                self.extra.setdefault(key, []).append(value)

    def row_due(self, env_steps: int) -> bool:
        """Whether ``maybe_row`` will emit a row at this step."""
        return env_steps >= self.next_row or env_steps >= self.total

    def maybe_row(self, env_steps: int, episodes: int, updates: int, epsilon: float, **extra: float) -> dict | None:
        """A row (written, shown, returned) when ``env_steps`` passed the next row's step or the end."""
        if not self.row_due(env_steps):
            return None
        now = time.perf_counter()
        dt = max(now - self.t_row, 1e-9)
        row = {
            "env_steps": env_steps,
            "episodes": episodes,
            "updates": updates,
            "return": float(np.mean(self.window)) if self.window else math.nan,
            "loss": float(np.mean(self.losses)) if self.losses else math.nan,
            "epsilon": epsilon,
            "env_steps_per_s": (env_steps - self.steps_at_row) / dt,
            "updates_per_s": (updates - self.updates_at_row) / dt,
            "wall_s": self.wall_before + now - self.t0,
            **{k: float(np.mean(v)) for k, v in self.extra.items()},
            **({"skipped_updates": float(self.skipped_updates)} if self.skipped_updates else {}),
            **extra,
        }
        self.rows.append(row)
        if self.writer:
            self.writer.write(row)
        self.bar.update(env_steps, row)
        self.window, self.losses, self.extra = [], [], {}
        self.t_row, self.steps_at_row, self.updates_at_row = now, env_steps, updates
        while self.next_row <= env_steps:
            self.next_row += self.log_every
        return row

    def close(self) -> None:
        self.bar.close()
        if self.writer:
            self.writer.close()


EVAL_SEED_OFFSET = 10_000  # evaluation envs are seeded apart from the training envs (same seeds at every point)


class Evaluator:
    """Greedy evaluation on fixed seeds: the learning curve (every ``eval_every`` env steps), the best policy seen
    (``save_best`` is called whenever a point beats it) and the final figures beside the env's reference policies.

    Every point plays the same ``eval_episodes`` episodes (seeds ``seed + EVAL_SEED_OFFSET + round``), so points
    differ by the policy only. Points are played as evaluation (``Progress.training`` off: CoDBC's teacher does not
    drive) and greedily, which draws no random number, so evaluating does not change the training run it measures.
    """

    def __init__(
        self,
        job: Any,
        make_env: Callable[[int], BatchedEnv] | None,
        save_best: Callable[[], None] | None = None,
        best: float = -math.inf,
        first_step: int = 0,
    ) -> None:
        self.episodes, self.every = int(job.eval_episodes), int(job.eval_every)
        self.seed = int(job.seed) + EVAL_SEED_OFFSET
        self.env_name, self.env_params = str(job.env), dict(job.env_params)
        self.messages = job.eval_messages
        self.make_env, self.save_best = make_env, save_best
        self.best, self.best_step = best, -1
        self.next = (first_step // self.every + 1) * self.every if self.every else 0
        self._env: BatchedEnv | None = None

    @property
    def enabled(self) -> bool:
        return self.episodes > 0 and self.make_env is not None

    def due(self, env_steps: int, total: int) -> bool:
        """Whether a curve point is owed at this step (every ``eval_every`` steps and at the end of the run)."""
        return self.enabled and self.every > 0 and (env_steps >= self.next or env_steps >= total)

    def returns(self, algo: Any, epsilon: float = 0.0) -> np.ndarray:
        """Per-episode returns of ``eval_episodes`` episodes on the fixed evaluation seeds."""
        if self._env is None:
            assert self.make_env is not None
            self._env = self.make_env(min(self.episodes, 256))
        training = algo.progress
        algo.progress = dataclasses.replace(training, training=False)
        hearing = cast(MessageSource, self.messages) if epsilon < 1.0 and isinstance(algo, HearsMessages) else "sent"
        try:
            with listening(algo, listening_for(algo, hearing, seed=self.seed)):
                return evaluate(self._env, algo, self.episodes, seed=self.seed, epsilon=epsilon)
        finally:
            algo.progress = training

    def point(self, algo: Any, env_steps: int) -> dict[str, float]:
        """One point of the curve (``eval_return``, ``eval_ci95``); keeps the policy if it is the best so far."""
        r = self.returns(algo)
        mean = float(r.mean())
        while self.next <= env_steps:
            self.next += self.every
        if mean > self.best:
            self.best, self.best_step = mean, env_steps
            if self.save_best is not None:
                self.save_best()
        return {"eval_return": mean, "eval_ci95": ci95_half(r, single=0.0)}

    def final(self, algo: Any, say: Callable[[str], None] | None = None) -> dict[str, Any]:
        """The trained policy's greedy return and CI, the best point of the curve and the reference policies'
        returns on the same number of episodes (the uniform random policy for every env, the same for every
        algorithm; the treadmill adds its best constant action, a tuned driver and its planners). ``say``: where
        a line goes as each part ends, when the env's references are slow enough to need them (the treadmill's
        planners: tens of seconds at 100 episodes, after the last training step)."""
        if not self.enabled:
            nan = math.nan
            return {"eval_return": nan, "eval_ci95": nan, "random_return": nan, "references": {}}
        from convoy.envs.registry import env_entry

        table = env_entry(self.env_name).references
        say = say if table is not None else None
        if say is not None:
            say(f"final evaluation: the greedy policy, then the reference policies, {self.episodes:,} episodes each")
        t0 = time.perf_counter()
        greedy = self.returns(algo)
        if say is not None:
            shown = f"{float(greedy.mean()):.3f} ± {ci95_half(greedy, single=0.0):.3f}"
            say(f"  greedy policy {shown} ({time.perf_counter() - t0:.1f} s)")
        if table is not None:  # the env's own references, its uniform random policy among them
            refs = table(self.env_params, self.episodes, self.seed, report=_reporter(say) if say else None)
        else:
            assert self._env is not None  # made by returns() above
            rand = evaluate_random(self._env, self.episodes, self.seed)
            refs = {"random": (float(rand.mean()), ci95_half(rand, single=0.0))}
        out: dict[str, Any] = {
            "eval_return": float(greedy.mean()),
            "eval_ci95": ci95_half(greedy, single=0.0),
            "random_return": float(refs["random"][0]),  # the same figure as references.random
            "references": {k: [float(m), float(c)] for k, (m, c) in refs.items()},
        }
        if self.best > -math.inf:
            out["best_eval_return"], out["best_eval_step"] = self.best, self.best_step
        return out

    def close(self) -> None:
        if self._env is not None:
            self._env.close()


def _reporter(say: Callable[[str], None]) -> Callable[[int, int, str, tuple[float, float], float, float | None], None]:
    """A line per reference policy as it ends, with the time the rest will take once one has been timed
    (``envs.registry.Report``)."""

    def report(k: int, of: int, name: str, result: tuple[float, float], seconds: float, left: float | None) -> None:
        rest = f"; about {left:.0f} s left" if left is not None and k < of else ""
        say(f"  reference {k}/{of} {name} {result[0]:.3f} ± {result[1]:.3f} ({seconds:.1f} s{rest})")

    return report


def write_artefacts(out_dir: str | Path, summary: dict[str, Any], rows: list[dict[str, Any]], title: str) -> None:
    """``summary.json`` and ``curve.png`` (the random policy's return as the baseline line)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    if rows:
        refs = summary.get("references") or {"random": [summary.get("random_return", math.nan), 0.0]}
        plot_curves(rows, out / "curve.png", title=title, references=refs)


class ProgressDisplay:
    """A live rich progress bar in a terminal; one plain line per metric row when output goes to a file or pipe
    (a bar redrawn into a log is unreadable); silent when disabled."""

    def __init__(self, total: int, enabled: bool) -> None:
        self.progress = None
        self.total = total
        self.lines = enabled and not sys.stdout.isatty()
        if not enabled or self.lines:
            return
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

        self.progress = Progress(
            TextColumn("[bold]train"),
            BarColumn(bar_width=24),
            MofNCompleteColumn(),
            TextColumn("{task.fields[info]}"),
            TimeRemainingColumn(),
        )
        self.progress.start()
        self.task = self.progress.add_task("train", total=total, info="")

    @staticmethod
    def describe(row: dict[str, Any]) -> str:
        text = (
            f"return {row['return']:.2f} · loss {row['loss']:.3f} · ε {row['epsilon']:.2f} · "
            f"{row['env_steps_per_s']:,.0f} steps/s · {row['updates_per_s']:,.0f} upd/s"
        )
        if "policy_lag" in row:
            text += f" · lag {row['policy_lag']:.1f} · actors {row.get('actors_alive', 0):.0f}"
        return text

    def counted(self, steps: int) -> str:
        """``2,000/3,000 steps``; past the budget the real count, saying why it is more: every env takes its step,
        so the last step of a batch of envs can go past the steps asked for."""
        if steps <= self.total:
            return f"{steps:>{len(f'{self.total:,}')},}/{self.total:,} steps"
        return f"{steps:,} steps (asked {self.total:,}: the last batch step went {steps - self.total:,} over)"

    def update(self, steps: int, row: dict[str, Any]) -> None:
        if self.lines:
            print(f"{self.counted(steps)} · {self.describe(row)}", flush=True)
        elif self.progress is not None:
            self.progress.update(self.task, completed=min(steps, self.total), info=self.describe(row))

    def close(self) -> None:
        if self.progress is not None:
            self.progress.stop()
