"""``convoy compare RUN…``: local runs side by side — their greedy curves in one plot and their figures in one table."""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.table import Table

from convoy.cli.args import add_command
from convoy.cli.rundir import run_folders
from convoy.validation import ConfigError

console = Console()


def load_group(path: Path) -> dict[str, Any]:
    """A run folder, or a population's (its ``seed-N`` runs as one group), as a group of seeds: the mean greedy
    curve with its CI, the final and best greedy returns over seeds, and the random reference."""
    from convoy.api.sweeps import greedy_curve
    from convoy.envs.registry import return_bounds
    from convoy.learner.metrics import read_rows
    from convoy.stats import mean_ci, mean_curve

    folders = [f for f in run_folders(path) if (f / "metrics.jsonl").is_file()]
    if not folders:
        raise ConfigError("RUN", f"{path} holds no run (no metrics.jsonl, nor seed-N/ folders with one); give a "
                          "folder convoy train wrote")  # fmt: skip
    curves, summaries = [], []
    for folder in folders:
        summary = json.loads((folder / "summary.json").read_text()) if (folder / "summary.json").is_file() else None
        steps, values, _ = greedy_curve(read_rows(folder), summary, int((summary or {}).get("env_steps", 0)))
        if len(steps):
            curves.append((steps, values))
        if summary is not None:
            summaries.append(summary)

    def over(key: str) -> dict[str, Any]:
        return mean_ci([float(s[key]) for s in summaries if isinstance(s.get(key), int | float)])

    bounds = return_bounds(str(summaries[0].get("env", ""))) if summaries else None
    return {"group": str(path), "runs": len(folders), "curve": mean_curve(curves), "bounds": bounds,
            "final": over("eval_return"), "best": over("best_eval_return"), "random": over("random_return"),
            "steps": max((int(s.get("env_steps", 0)) for s in summaries), default=0)}  # fmt: skip


def cmd_compare(args: argparse.Namespace) -> int:
    """Compare local runs: greedy curves side by side.

    Each RUN is a folder written by convoy train: one run, or a population's (its seeds are one group, drawn as the
    mean over seeds with its 95 % CI band). Prints each group's final greedy return, best greedy point and random
    reference (mean ± 95 % CI over its seeds; a single seed's figure alone, with no CI) and plots the greedy curves
    in one PNG: --plot, or compare.png in the folder that holds the runs.
    """
    from convoy.analysis.curves import plot_groups

    groups = [load_group(Path(run)) for run in args.runs]
    table = Table(title="greedy return: mean ± 95 % CI over each group's seeds")
    for col in ("run", "seeds", "env steps", "final greedy", "best greedy point", "random"):
        table.add_column(col, justify="left" if col == "run" else "right")

    def fmt(stats: dict[str, Any]) -> str:
        if stats["mean"] is None:
            return "–"
        return f"{stats['mean']:.3f}" if stats["n"] < 2 else f"{stats['mean']:.3f} ± {stats['ci95']:.3f}"

    for g in groups:
        table.add_row(g["group"], str(g["runs"]), f"{g['steps']:,}", fmt(g["final"]), fmt(g["best"]), fmt(g["random"]))
    console.print(table)
    if any(g["final"]["n"] == 1 for g in groups):
        console.print("a group of one seed has no CI over seeds: its figures stand alone", highlight=False)
    plot = Path(args.plot) if args.plot else default_plot([Path(run) for run in args.runs])
    plot_groups(groups, plot, title="greedy evaluation (mean ± 95 % CI over seeds)")
    console.print(f"wrote {plot}", highlight=False)
    return 0


def default_plot(runs: list[Path]) -> Path:
    """``compare.png`` beside the compared runs: in the folder that holds them (their parents' common folder),
    not wherever the command happens to run."""
    parents = [str(run.resolve().parent) for run in runs]
    where = Path(os.path.commonpath(parents))
    cwd = Path.cwd()
    return (where.relative_to(cwd) if where.is_relative_to(cwd) else where) / "compare.png"


def add_compare_parser(sub: argparse._SubParsersAction) -> None:
    p = add_command(sub, "compare", cmd_compare)
    p.add_argument("runs", nargs="+", metavar="RUN", help="a run's folder, or a population's (its seed-N runs)")
    p.add_argument(
        "--plot",
        metavar="PATH",
        help="the plot's file (default: compare.png beside the runs, in the folder that holds them: runs/compare.png "
        "for runs/a runs/b)",
    )
