"""Metric rows to disk (JSONL and CSV, appended as they come) and learning curves to PNG."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import IO, Any

import numpy as np

from convoy.output import json_safe, pyplot, save_figure


class MetricsWriter:
    """Appends one row per call to ``metrics.jsonl`` and ``metrics.csv`` in ``out_dir`` (flushed each row).

    ``resume_at``: a learner restarted from a checkpoint taken at that env step keeps the rows up to it and drops
    the ones written after it (their steps are being redone), so the history has neither gaps nor duplicates.
    """

    def __init__(self, out_dir: str | Path, resume_at: int | None = None) -> None:
        self.out_dir = Path(out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.rows: list[dict[str, Any]] = read_rows(self.out_dir) if resume_at is not None else []
        self.rows = [r for r in self.rows if r.get("env_steps", 0) <= (resume_at or 0)]
        self._jsonl: IO[str] = open(self.out_dir / "metrics.jsonl", "w")  # noqa: SIM115 (closed in close())
        self._csv_fh: IO[str] = open(self.out_dir / "metrics.csv", "w", newline="")  # noqa: SIM115
        self._csv: csv.DictWriter | None = None
        kept, self.rows = self.rows, []
        for row in kept:
            self.write(row)

    def write(self, row: dict[str, Any]) -> None:
        self.rows.append(row)
        self._jsonl.write(json.dumps(json_safe(row)) + "\n")
        self._jsonl.flush()
        if self._csv is None or not set(row) <= set(self._csv.fieldnames):
            self._rewrite_csv()  # the first row, or a column that appears later (e.g. once updates begin)
        else:
            self._csv.writerow(row)
        self._csv_fh.flush()

    def _rewrite_csv(self) -> None:
        """Write the CSV afresh with every column seen so far (rows lacking one leave it empty)."""
        fields = list(dict.fromkeys(k for r in self.rows for k in r))
        self._csv_fh.seek(0)
        self._csv_fh.truncate()
        self._csv = csv.DictWriter(self._csv_fh, fieldnames=fields, extrasaction="ignore")
        self._csv.writeheader()
        self._csv.writerows(self.rows)

    def close(self) -> None:
        self._jsonl.close()
        self._csv_fh.close()


def read_rows(out_dir: str | Path) -> list[dict[str, Any]]:
    """The rows of ``out_dir/metrics.jsonl`` (None back to NaN); a torn last line is skipped."""
    path = Path(out_dir) / "metrics.jsonl"
    rows: list[dict[str, Any]] = []
    if not path.is_file():
        return rows
    for line in path.read_text().splitlines():
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            continue
        rows.append({k: (math.nan if v is None else v) for k, v in row.items()})
    return rows


def plot_curves(
    rows: list[dict[str, float]], path: str | Path, title: str, references: dict[str, list[float]] | None = None
) -> Path:
    """The learning curve: the greedy evaluation with its 95 % CI band (the figure to read), the ε-greedy training
    return (episodes that ended in each row; short crashed episodes weigh in it) and the reference policies as
    dashed lines; speed beside it."""
    plt = pyplot()

    path = Path(path)
    steps = [r["env_steps"] for r in rows]
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 3.6))
    ax1.plot(steps, [r["return"] for r in rows], color="tab:blue", alpha=0.35, lw=1, label="training return (ε-greedy)")
    points = [r for r in rows if not math.isnan(r.get("eval_return", math.nan))]
    if points:
        x = np.array([r["env_steps"] for r in points])
        y = np.array([r["eval_return"] for r in points])
        ci = np.array([r.get("eval_ci95", 0.0) for r in points])
        ax1.plot(x, y, color="tab:blue", lw=2, marker="o", ms=3, label="greedy evaluation (95 % CI)")
        ax1.fill_between(x, y - ci, y + ci, color="tab:blue", alpha=0.2)
    colours = iter(["grey", "tab:orange", "tab:green", "tab:red", "tab:purple"])
    for name, (mean, _) in (references or {}).items():
        if not math.isnan(mean):
            ax1.axhline(mean, ls="--", lw=1, color=next(colours, "black"), label=name)
    ax1.set_xlabel("env steps")
    ax1.set_ylabel("episode return (mean over agents)")
    ax1.legend(loc="best", fontsize=7)
    ax1.set_title(title)
    ax2.plot(steps, [r["env_steps_per_s"] for r in rows], label="env steps/s")
    ax2.plot(steps, [r["updates_per_s"] for r in rows], label="updates/s")
    ax2.set_xlabel("env steps")
    ax2.set_yscale("log")
    ax2.legend(loc="best", fontsize=8)
    ax2.set_title("speed")
    return save_figure(fig, path)
