"""Metric rows to disk (JSONL and CSV, appended as they come) and learning curves to PNG."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import IO, Any


class MetricsWriter:
    """Appends one row per call to ``metrics.jsonl`` and ``metrics.csv`` in ``out_dir`` (flushed each row)."""

    def __init__(self, out_dir: str | Path) -> None:
        self.out_dir = Path(out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self._jsonl: IO[str] = open(self.out_dir / "metrics.jsonl", "w")  # noqa: SIM115 (closed in close())
        self._csv_fh: IO[str] = open(self.out_dir / "metrics.csv", "w", newline="")  # noqa: SIM115
        self._csv: csv.DictWriter | None = None

    def write(self, row: dict[str, Any]) -> None:
        clean = {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in row.items()}
        self._jsonl.write(json.dumps(clean) + "\n")
        self._jsonl.flush()
        if self._csv is None:
            self._csv = csv.DictWriter(self._csv_fh, fieldnames=list(row))
            self._csv.writeheader()
        self._csv.writerow(row)
        self._csv_fh.flush()

    def close(self) -> None:
        self._jsonl.close()
        self._csv_fh.close()


def plot_curves(rows: list[dict[str, float]], path: str | Path, title: str, baseline: float | None = None) -> Path:
    """Return and speed against env steps; the random policy's return as a dashed line when given."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    steps = [r["env_steps"] for r in rows]
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 3.6))
    ax1.plot(steps, [r["return"] for r in rows], label="training return (ε-greedy)")
    if baseline is not None and not math.isnan(baseline):
        ax1.axhline(baseline, ls="--", color="grey", label="random policy")
    ax1.set_xlabel("env steps")
    ax1.set_ylabel("episode return (mean over agents)")
    ax1.legend(loc="best", fontsize=8)
    ax1.set_title(title)
    ax2.plot(steps, [r["env_steps_per_s"] for r in rows], label="env steps/s")
    ax2.plot(steps, [r["updates_per_s"] for r in rows], label="updates/s")
    ax2.set_xlabel("env steps")
    ax2.set_yscale("log")
    ax2.legend(loc="best", fontsize=8)
    ax2.set_title("speed")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
