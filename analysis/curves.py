"""Plots of sweep groups: learning curves (the mean over seeds with its 95 % CI band, one colour per group) and
final returns against a grid axis."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from convoy.output import pyplot, save_figure


def plot_groups(
    groups: list[dict[str, Any]],
    path: str | Path,
    title: str,
    references: dict[str, float] | None = None,
    xlabel: str = "env steps",
    ylabel: str = "greedy return",
) -> Path:
    """A PNG of each group's ``curve`` (``env_steps``, ``mean``, ``ci95``) as a line with a shaded band, and each
    reference return as a dashed horizontal line. A group's ``bounds`` (the returns its env allows: a success rate's
    [0, 1]) clip its band: a t-interval over few seeds runs past them (−0.3 to 1.5 on a success rate), and no
    return lies there."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 4.2))
    draw_groups(ax, groups)
    for i, (name, value) in enumerate((references or {}).items()):
        ax.axhline(value, color=f"C{7 + i % 3}", linestyle="--", linewidth=1, label=name)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    finish(ax)
    return _save(fig, path)


def plot_panels(panels: dict[str, list[dict[str, Any]]], path: str | Path, title: str) -> Path:
    """A PNG of one ``plot_groups`` panel per title in ``panels`` (three a row, each on its own return axis: one
    group's wide band must not flatten the others): a study's experiment files side by side, a group's
    ``linestyle`` and ``color`` kept (a recipe set aside dashed beside the current one in the same colour)."""
    plt = pyplot()
    cols = min(3, len(panels))
    rows = -(-len(panels) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.6 * cols, 3.6 * rows), squeeze=False)
    for ax, (name, groups) in zip(axes.flat, panels.items(), strict=False):
        shown = draw_groups(ax, groups)
        if shown:  # a set-aside group's band (2 seeds: t = 12.7) runs off the axis rather than flatten the study
            low, high = min(shown), max(shown)
            pad = 0.05 * (high - low) or 1.0
            ax.set_ylim(low - pad, high + pad)
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("env steps")
        finish(ax)
    for ax in axes.flat[len(panels) :]:
        ax.set_visible(False)
    for ax in axes[:, 0]:
        ax.set_ylabel("greedy return")
    fig.suptitle(title)
    return _save(fig, path)


def draw_groups(ax: Any, groups: list[dict[str, Any]]) -> list[float]:
    """Each group's ``curve`` (``env_steps``, ``mean``, ``ci95``) as a line with a shaded band on ``ax``; the returns
    the axis must show: every line, and the bands of the solid ones."""
    import numpy as np

    shown: list[float] = []
    for group in groups:
        curve = group["curve"]
        keep = [i for i, m in enumerate(curve["mean"]) if m is not None]
        if not keep:
            continue
        x = np.array([curve["env_steps"][i] for i in keep], dtype=float)
        y = np.array([curve["mean"][i] for i in keep], dtype=float)
        ci = np.array([curve["ci95"][i] or 0.0 for i in keep], dtype=float)
        n = max(curve["n"][i] for i in keep)
        (line,) = ax.plot(x, y, label=f"{group['group']} (n={n})", linestyle=group.get("linestyle", "-"),
                          color=group.get("color"))  # fmt: skip
        low, high = band(y, ci, group.get("bounds"))
        ax.fill_between(x, low, high, color=line.get_color(), alpha=0.2, linewidth=0)
        solid = group.get("linestyle", "-") == "-"
        shown += [float(low.min()), float(high.max())] if solid else [float(y.min()), float(y.max())]
    return shown


def finish(ax: Any) -> None:
    """Grid and legend, or a note where no group has a greedy evaluation yet."""
    ax.grid(alpha=0.3)
    if ax.get_legend_handles_labels()[1]:
        ax.legend(fontsize=7, loc="best")
    else:  # a job that has not reached its first greedy evaluation yet
        ax.text(0.5, 0.5, "no greedy evaluation yet", ha="center", va="center", transform=ax.transAxes)


def band(mean: Any, ci: Any, bounds: Any = None) -> tuple[Any, Any]:
    """The band ``mean ± ci``, clipped to ``bounds`` (lowest, highest) when given."""
    import numpy as np

    low, high = np.asarray(mean) - ci, np.asarray(mean) + ci
    if bounds:
        low, high = np.clip(low, *bounds), np.clip(high, *bounds)
    return low, high


def plot_final_by(
    groups: list[dict[str, Any]],
    path: str | Path,
    title: str,
    x: str,
    lines: str,
    xlabel: str,
    ylabel: str = "final greedy return",
    references: tuple[str, ...] = ("random", "scripted"),
) -> Path:
    """A PNG of each group's final return (mean ± 95 % CI) against one grid axis ``x`` (log₂), one line per value
    of another axis ``lines`` (Fig. 4a: return against the number of agents, one line per algorithm), and the
    named reference policies' returns (each group's own ``references``: its env changes along ``x``) dashed."""
    plt = pyplot()

    series: dict[str, list[tuple[float, float, float]]] = {}
    refs: dict[str, dict[float, float]] = {}  # each reference policy's return at each x (its own env)
    for group in groups:
        point, final = group["point"], group["final"]
        if final["mean"] is not None:
            series.setdefault(str(point.get(lines)), []).append((point[x], final["mean"], final["ci95"]))
        for name, value in (group.get("references") or {}).items():
            if name in references:
                refs.setdefault(name, {})[point[x]] = value
    fig, ax = plt.subplots(figsize=(6.5, 4))
    for name, pts in series.items():
        xs, ys, cs = zip(*sorted(pts), strict=True)
        ax.errorbar(xs, ys, yerr=cs, marker="o", capsize=3, label=name)
    for i, (name, by_x) in enumerate(refs.items()):
        at = sorted(by_x)
        ax.plot(at, [by_x[v] for v in at], linestyle="--", color=f"C{7 + i % 3}", linewidth=1, label=name)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_xscale("log", base=2)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return _save(fig, path)


def _save(fig: Any, path: str | Path) -> Path:

    return save_figure(fig, path, dpi=100)
