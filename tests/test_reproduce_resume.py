"""``convoy reproduce`` killed outright — the command, its local service and every job process, as when a machine's
session ends — and run again goes on from the jobs' checkpoints instead of training anew."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from convoy.cli.main import main
from convoy.services.store import JobStore
from tests.proctree import descendants

pytestmark = pytest.mark.timeout(900)

FIGURE = """
name = "tiny"
[base]
env = "referential"
steps = 24000
num_envs = 8
eval_every = 4000
eval_episodes = 16
log_every = 1000
checkpoint_every = 2000
algo_params = { hidden = [32], learning_starts = 200 }
[grid]
algo = ["idqn"]
seed = [0, 1]
[scales.quick]
note = "two seeds of 24,000 steps, packed as one population"
[figure]
id = "fig8"
title = "Fig. 8: a tiny stand-in"
held_out_episodes = 0
claims = [{ text = "a number", group = "algo=idqn", paper = 0.5, comparable = false }]
"""


def trained_past_a_checkpoint(data: Path) -> bool:
    """A run of the service's jobs has a checkpoint and has logged 2,000 env steps past the first one's."""
    if not any(data.glob("**/checkpoint.pt")):
        return False
    steps = 0
    for path in data.glob("**/metrics.jsonl"):
        with contextlib.suppress(OSError):
            for line in path.read_text().splitlines():
                with contextlib.suppress(ValueError):
                    steps = max(steps, int(json.loads(line).get("env_steps", 0)))
    return steps >= 4000


def rows(data: Path) -> list[dict[str, object]]:
    """Seed 0's metric rows in its run folder (each holds its learner's wall clock: a retrained row differs)."""
    path = next(data.glob("**/seed-0/metrics.jsonl"))
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def test_a_killed_reproduce_goes_on_from_its_checkpoints_when_run_again(tmp_path: Path) -> None:
    (tmp_path / "exp").mkdir()
    (tmp_path / "exp" / "fig8.toml").write_text(FIGURE)
    argv = ["reproduce", "fig8", "--scale", "quick", "--experiments", str(tmp_path / "exp"), "--data",
            str(tmp_path / "data"), "--docs", str(tmp_path / "docs"), "--page", str(tmp_path / "page.md"),
            "--max-processes", "3"]  # fmt: skip
    first = subprocess.Popen([sys.executable, "-m", "convoy.cli", *argv], start_new_session=True,
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    killed: list[int] = []
    try:
        t_end = time.monotonic() + 600
        while not trained_past_a_checkpoint(tmp_path / "data"):
            assert first.poll() is None, "the first run ended before it was killed"
            assert time.monotonic() < t_end, "no checkpoint at 4,000 steps within 10 minutes"
            time.sleep(0.5)
    finally:  # every process at once, no chance to clean up: the end of a session
        killed = [first.pid, *descendants(first.pid)]
        for pid in killed:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        first.wait(30)
    assert len(killed) >= 3, "the command, its service and the job's host were all running"
    before = rows(tmp_path / "data")
    store = JobStore(tmp_path / "data" / "quick" / "service" / "jobs.sqlite")
    population = next(r for r in store.list() if not r.progress.get("packed_in"))
    at_kill = store.last_step(population.id) or 0
    store.close()
    assert 0 < at_kill < 24000

    assert main(argv) == 0  # the same command again
    record = json.loads((tmp_path / "docs" / "fig8.json").read_text())
    assert record["groups"][0]["states"] == {"completed": 2} and record["groups"][0]["final"]["n"] == 2
    store = JobStore(tmp_path / "data" / "quick" / "service" / "jobs.sqlite")
    try:
        reasons = [t["reason"] for t in store.transitions(population.id)]
        assert "resuming from its last checkpoint" in reasons, reasons
        for member in (r for r in store.list() if r.progress.get("packed_in")):
            steps = [int(m["env_steps"]) for m in store.metrics(member.id)]
            assert steps == sorted(steps) and steps[-1] == 24000  # one history, cut at the checkpoint, no restart
    finally:
        store.close()
    after = rows(tmp_path / "data")
    assert after[:2] == before[:2], "the rows before the checkpoint were kept, not trained again"
