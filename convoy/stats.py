"""Statistics every report shares: the 95 % confidence half-width of a mean."""

from __future__ import annotations

import numpy as np


def ci95_half(x: np.ndarray, single: float = float("nan")) -> float:
    """Half-width of the normal 95 % confidence interval of the mean of ``x`` (``single`` when len(x) < 2)."""
    x = np.asarray(x, dtype=np.float64)
    return float(1.96 * x.std(ddof=1) / np.sqrt(len(x))) if len(x) > 1 else single
