"""Start ``convoy serve`` as a real process on free loopback ports for the API tests, and clean up by PID.

``Service.start()`` waits for ``/healthz``; ``kill()`` SIGKILLs the API (the restart test) and ``stop()`` also ends
every job host the store recorded, so no test leaves processes behind whatever it did.
"""

from __future__ import annotations

import json
import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx

from convoy.protocol.session import free_port
from tests.pace import paced

TOKEN = "test-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
SMALL_JOB: dict[str, Any] = {
    "algo": "ma-mesn",
    "env": "treadmill",
    "env_params": {"n_agents": 2, "length": 30, "width": 12, "max_steps": 50},
    "algo_params": {"hidden": [32], "learning_starts": 200},
    "num_envs": 8,
    "log_every": 1000,
    "checkpoint_every": 5000,
    "eval_episodes": 4,
}


class Service:
    def __init__(self, data: Path, port: int | None = None, max_processes: int = 8) -> None:
        self.data, self.max_processes = data, max_processes
        self.port = port or free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.proc: subprocess.Popen | None = None
        self.client = httpx.Client(base_url=self.url, timeout=30)

    def start(self, timeout: float = 120.0) -> Service:
        """Start ``convoy serve`` and wait for /healthz (a generous bound: a loaded 2-core machine can take a minute);
        a server that does not answer in time is killed, not left behind."""
        env = {**os.environ, "CONVOY_API_TOKEN": TOKEN}
        cmd = [sys.executable, "-m", "convoy.cli", "serve", "--port", str(self.port), "--data", str(self.data)]
        cmd += ["--max-processes", str(self.max_processes)]
        log = open(self.data.parent / f"serve-{self.port}.log", "ab")  # noqa: SIM115
        self.data.mkdir(parents=True, exist_ok=True)
        self.proc = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT)
        log.close()
        timeout = paced(timeout)
        t_end = time.monotonic() + timeout
        while time.monotonic() < t_end:
            if self.proc.poll() is not None:
                raise RuntimeError(f"convoy serve exited with {self.proc.returncode}")
            try:
                if self.client.get("/healthz").status_code == 200:
                    return self
            except httpx.TransportError:
                pass
            time.sleep(0.2)
        self.stop()
        raise TimeoutError(f"convoy serve did not answer /healthz within {timeout:.0f} s (stopped it)")

    def kill(self) -> None:
        """SIGKILL the API process only (its jobs keep running)."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)

    def host_pids(self) -> list[int]:
        path = self.data / "jobs.sqlite"
        if not path.is_file():
            return []
        with sqlite3.connect(path) as db:
            rows = db.execute("SELECT progress FROM jobs").fetchall()
        return [int(json.loads(p).get("host_pid", 0)) for (p,) in rows if p and json.loads(p).get("host_pid")]

    def stop(self) -> None:
        """End the API and every job host it started (their process groups), by PID."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
        for pid in self.host_pids():
            for sig in (signal.SIGTERM, signal.SIGKILL):
                try:
                    os.killpg(pid, sig)
                except (ProcessLookupError, PermissionError):
                    break
                time.sleep(1.0)
        self.client.close()

    def wait(
        self, job_id: str, pred: Any, timeout: float = 90.0, what: str = "", every: float = 0.3, pace: bool = True
    ) -> dict[str, Any]:
        """Poll GET /jobs/{id} until ``pred(view)``; the last view otherwise (with a clear assertion)."""
        return self.wait_for(f"/jobs/{job_id}", pred, timeout, what, every, pace)

    def wait_for(
        self, url: str, pred: Any, timeout: float = 90.0, what: str = "", every: float = 0.3, pace: bool = True
    ) -> dict[str, Any]:
        """Poll GET ``url`` until ``pred(answer)``; a clear assertion with the last answer otherwise. ``timeout``
        is the reference machine's seconds (``tests/pace.py``) unless ``pace`` is off: a bound the product claims."""
        timeout = paced(timeout) if pace else timeout
        t_end = time.monotonic() + timeout
        view: dict[str, Any] = {}
        while time.monotonic() < t_end:
            view = self.client.get(url).json()
            if pred(view):
                return view
            time.sleep(every)
        raise AssertionError(f"timed out waiting for {what or 'condition'}: {view}")
