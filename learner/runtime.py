"""Process-level settings for a learner: torch threads and a glibc allocator that keeps big buffers mapped.

Why the allocator: an update at batch 1024 on the treadmill's 4096-wide layers allocates activations of tens of MB.
glibc serves blocks above its mmap threshold (at most 32 MB, adaptive) with fresh ``mmap`` calls, so every update
faults ~400 MB of pages in and hands them back — measured at a third of the update time at batch 1024. Raising the
threshold and the trim threshold makes those blocks come from the heap and stay there, the same effect as
``MALLOC_MMAP_THRESHOLD_`` in the environment, but set from inside the process so nobody has to remember it.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

import torch

_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
_tuned = False


def keep_large_allocations(threshold_bytes: int = 1 << 30) -> bool:
    """Serve allocations below ``threshold_bytes`` from the heap and never trim it; True where it applied."""
    global _tuned
    if _tuned:
        return True
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        ok = libc.mallopt(_M_MMAP_THRESHOLD, threshold_bytes) == 1
        ok = ok and libc.mallopt(_M_TRIM_THRESHOLD, 2 * threshold_bytes) == 1
    except (OSError, AttributeError):  # not glibc (musl, …): nothing to tune
        return False
    _tuned = ok
    return ok


def configure_learner(threads: int) -> None:
    """Thread count for torch's intra-op pool plus the allocator setting above."""
    torch.set_num_threads(threads)
    keep_large_allocations()
