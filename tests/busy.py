"""Load the machine's cores for a test: busy-loop processes, ended by PID whatever the test did.

The distributed runtime must tell a normal end from a crash, and scale live, on a machine busy with other work (the
2-core boxes this project runs on often are): the tests of that run their job beside these processes.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
from collections.abc import Iterator

BUSY_CORES = 2  # the 2-core machine the README names: both cores busy


@contextlib.contextmanager
def busy_cores(n: int = BUSY_CORES) -> Iterator[list[int]]:
    """``n`` processes that spin on a core each (``while True: pass``) for the ``with`` block; their PIDs."""
    procs: list[subprocess.Popen[bytes]] = []
    try:
        for _ in range(n):
            procs.append(subprocess.Popen([sys.executable, "-c", "while True: pass"], stdin=subprocess.DEVNULL))
        yield [p.pid for p in procs]
    finally:
        for p in procs:
            with contextlib.suppress(ProcessLookupError):
                os.kill(p.pid, signal.SIGKILL)
            p.wait(30)
