"""How much slower than the suite's reference machine this one runs right now, for the tests' fixed clocks.

A wait for a job, a server's start-up or a hang guard is a number of seconds set on one idle 2-core x86-64 machine;
a loaded or slower machine needs more, and a test that fails there says nothing about the code. ``paced(s)`` is ``s``
times :func:`slowness`: the wall time of a fixed piece of Python work now against its time on that machine (measured
as CPU time there, so ``slowness`` is 1 there when idle and ~2 with both cores shared with another training run).
Bounds that are the product's claim on a loaded machine (live scaling within 30 s beside busy cores) stay fixed.
"""

from __future__ import annotations

import time

REFERENCE_S = 0.024  # _work's CPU time on the reference machine (its wall time when idle)
MOST = 10.0  # a hang is still caught on a very slow or loaded machine


def _work() -> int:
    total = 0
    for i in range(400_000):
        total += i * i
    return total


def slowness() -> float:
    """The median of three timings of ``_work`` over its reference time, within [1, ``MOST``]: never a shorter
    wait than the test names."""
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        _work()
        times.append(time.perf_counter() - t0)
    return min(MOST, max(1.0, sorted(times)[1] / REFERENCE_S))


def paced(seconds: float) -> float:
    """``seconds`` on the reference machine, as long as this machine needs for the same work now."""
    return seconds * slowness()
