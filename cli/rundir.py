"""Run directories: one run per directory, never two by accident.

Two ``convoy train`` runs writing one directory interleave ``metrics.jsonl`` and overwrite each other's
checkpoints, and a second run into a finished run's directory would silently replace (or, distributed, resume)
it. So a run claims its directory: an exclusive ``flock`` on ``.convoy.lock`` for as long as it runs (released by
the kernel when the process dies, so a crash leaves no stale lock), and a directory that already holds a run's
files is only reused when the user says ``--overwrite``. Without ``--out`` the default directory gets a free
numbered suffix instead.
"""

from __future__ import annotations

import fcntl
import os
import shutil
from pathlib import Path
from typing import IO

from convoy.validation import ConfigError

LOCK = ".convoy.lock"
LAUNCH = "launch.json"  # how the run was started (in this process or actors over Zenoh): --resume goes on the same way
RUN_FILES = ("checkpoint.pt", "metrics.jsonl", "summary.json")  # what makes a directory hold a run
# What a run writes, and all that --overwrite removes (never anything else a user keeps beside it).
ARTEFACTS = (*RUN_FILES, "best.pt", "checkpoint.previous.pt", "replay.npz", "replay.previous.npz", "metrics.csv",
             "curve.png", "checkpoint.unreadable", "job.json")  # fmt: skip


def run_folders(path: Path) -> list[Path]:
    """``path`` and the folders of a population's runs in it (``seed-N``)."""
    return [path, *sorted(p for p in path.glob("seed-*") if p.is_dir())]


def holds_run(path: Path) -> bool:
    return any((folder / name).exists() for folder in run_folders(path) for name in RUN_FILES)


def free_default(path: Path) -> Path:
    """``path`` if it holds no run, else the first of ``path-2``, ``path-3``, … that does not."""
    candidate, n = path, 1
    while holds_run(candidate):
        n += 1
        candidate = path.with_name(f"{path.name}-{n}")
    return candidate


class RunDir:
    """The claim on one run directory; ``release()`` (or process exit) gives it up."""

    def __init__(self, path: Path, handle: IO[str]) -> None:
        self.path, self._handle = path, handle

    def release(self) -> None:
        if not self._handle.closed:
            fcntl.flock(self._handle, fcntl.LOCK_UN)
            self._handle.close()


def claim(path: Path, overwrite: bool = False, resume: bool = False) -> RunDir:
    """Lock ``path`` for this run; ConfigError naming ``--out`` and the fix when another run has it or holds it
    (``resume``: the run it holds goes on, so it must hold one)."""
    if resume and not holds_run(path):
        raise ConfigError("--resume", f"{path} holds no run to resume (no checkpoint.pt, metrics or summary)")
    path.mkdir(parents=True, exist_ok=True)
    handle = open(path / LOCK, "a+")  # noqa: SIM115 - held for the run's lifetime
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        handle.seek(0)
        owner = handle.read().strip() or "?"
        handle.close()
        raise ConfigError(
            "--out", f"{path} is being written by another run (pid {owner}); wait for it or choose another --out"
        ) from None
    if holds_run(path) and not resume:
        if not overwrite:
            fcntl.flock(handle, fcntl.LOCK_UN)
            handle.close()
            raise ConfigError(
                "--out",
                f"{path} holds an earlier run ({', '.join(n for n in RUN_FILES if (path / n).exists()) or 'seed-N/'});"
                f" choose another --out, add --overwrite to replace it, or go on with it: --resume {path}",
            )
        for folder in run_folders(path):
            for name in ARTEFACTS:
                (folder / name).unlink(missing_ok=True)
    handle.seek(0)
    handle.truncate()
    handle.write(f"{os.getpid()}\n")
    handle.flush()
    return RunDir(path, handle)


def discard_unstarted(path: Path, made: bool) -> None:
    """Undo a run refused before it trained (no checkpoint in ``path`` or its seeds' folders), so nothing there reads
    as a run to ``--resume``: the folder itself when this command ``made`` it, else only the run's own files."""
    if any((folder / name).exists() for folder in run_folders(path) for name in ("checkpoint.pt", "best.pt")):
        return
    if made:
        shutil.rmtree(path, ignore_errors=True)
        return
    for folder in run_folders(path):
        for name in (*ARTEFACTS, LAUNCH, LOCK):
            (folder / name).unlink(missing_ok=True)
