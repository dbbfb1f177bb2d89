"""How Convoy writes what it measured: padded Markdown tables, PNG figures, and JSON without NaN.

One helper each, for the product (metrics files, Table 1, curves, the REST API) and the benchmarks alike.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any


def markdown_table(header: list[str], rows: list[list[str]], right: list[bool]) -> str:
    """A padded Markdown table (``right``: which columns are numbers, right-aligned), readable as printed."""
    widths = [max(len(r[j]) for r in [header, *rows]) for j in range(len(header))]

    def line(cells: list[str]) -> str:
        padded = (s.rjust(w) if r else s.ljust(w) for s, w, r in zip(cells, widths, right, strict=True))
        return "| " + " | ".join(padded) + " |"

    rule = "|" + "|".join("-" * (w + 1) + ":" if r else "-" * (w + 2) for w, r in zip(widths, right, strict=True)) + "|"
    return "\n".join([line(header), rule, *(line(r) for r in rows)])


def pyplot() -> Any:
    """``matplotlib.pyplot`` on the Agg backend, so figures render headless (no display, no GUI toolkit).

    The one place Convoy picks matplotlib's backend: every module that plots gets pyplot here, imported lazily so
    that importing the module costs nothing until it draws.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig: Any, path: str | Path, dpi: int = 110) -> Path:
    """A matplotlib figure as a PNG at ``path`` (folders made), laid out tight; the figure is closed."""
    plt = pyplot()

    path = Path(path)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def json_safe(value: Any) -> Any:
    """``value`` with every NaN or infinite float as None, through dicts, lists and tuples: JSON has neither."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    return value
