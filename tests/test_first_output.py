"""Slow commands say at once that they started: ``convoy serve`` before its imports, ``convoy analyze`` before
loading its checkpoint, then its recording's progress with an estimate of the time left (``convoy.cli.entry``)."""

from __future__ import annotations

import contextlib
import os
import queue
import signal
import subprocess
import sys
import threading
from pathlib import Path

from convoy.algos.checkpoint import save_checkpoint
from convoy.algos.registry import make_algorithm
from convoy.config import job_config
from convoy.envs import make_batched
from convoy.protocol.session import free_port
from tests.pace import paced

FIRST_LINE_S = 2.0  # the line is printed before any heavy import: ~0.1 s, loaded or not


def start(args: list[str]) -> tuple[subprocess.Popen, queue.Queue]:
    """``python -m convoy.cli ARGS`` with stdout and stderr merged; its lines arrive on the queue (None at EOF)."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    cmd = [sys.executable, "-m", "convoy.cli", *args]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    lines: queue.Queue = queue.Queue()

    def pump() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.put(line.rstrip("\n"))
        lines.put(None)

    threading.Thread(target=pump, daemon=True).start()
    return proc, lines


def stop(proc: subprocess.Popen) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.kill(proc.pid, signal.SIGTERM)
    try:
        proc.wait(30)
    except subprocess.TimeoutExpired:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(30)


def test_serve_says_it_is_starting_before_its_imports(tmp_path: Path) -> None:
    proc, lines = start(["serve", "--host", "127.0.0.1", "--port", str(free_port()), "--data", str(tmp_path)])
    try:
        first = lines.get(timeout=paced(FIRST_LINE_S))
        assert first is not None and first.startswith("convoy serve: starting"), first
        banner = lines.get(timeout=300)  # then the banner, once it is up
        assert banner is not None and banner.startswith("convoy serve: http://127.0.0.1:"), banner
    finally:
        stop(proc)


def test_analyze_says_it_is_starting_then_reports_its_progress(tmp_path: Path) -> None:
    job = job_config(algo="ma-mesn", env="treadmill", algo_params={"hidden": (16,)}, device="cpu", seed=5,
                     env_params={"length": 30, "width": 12})  # fmt: skip
    env = make_batched(job.env, 2, **job.env_params)
    agent = make_algorithm("ma-mesn", env.spec, job.algo_config(), device="cpu", seed=5)
    env.close()
    ckpt = save_checkpoint(tmp_path / "best.pt", agent, job, {"env_steps": 0, "episodes": 0, "updates": 0})
    args = ["analyze", str(ckpt), "--samples", "600", "--num-envs", "8", "--episodes", "8", "--repeats", "2",
            "--device", "cpu", "--out", str(tmp_path / "analysis")]  # fmt: skip
    proc, lines = start(args)
    try:
        first = lines.get(timeout=paced(FIRST_LINE_S))
        assert first is not None and first.startswith("convoy analyze: starting"), first
        seen = []
        while (line := lines.get(timeout=600)) is not None:
            seen.append(line)
        assert proc.wait(60) == 0, seen
    finally:
        stop(proc)
    progress = [s for s in seen if s.startswith("convoy analyze: recording")]
    assert progress and "left" in progress[0] and "600 samples" in progress[-1], seen
    assert any("100 %" in s for s in progress) and any("return figures" in s for s in seen), seen
