"""Many hosts for real: a router, a learner host and two actor hosts, each in its own Linux network namespace with
its own address, joined only by veth links to a bridge in the router's namespace (``.ci/run`` installs iproute2).

One actor host's link is cut for 10 s and restored mid-run: the job must complete with its full step count, its
learner never restarting (nothing acknowledged is lost: the learner's replay and counters live in one process),
and the cut host's actors must deliver again after the link returns. Every namespace, link and process is removed
by name and PID at the end.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from convoy.config import RuntimeConfig
from tests.multihost import Hosts, MultiHostJob, available

STEPS = 1_000_000  # so the job outlasts the 10 s cut: the uncut host alone can do ~300 k in it on a quiet machine

pytestmark = [
    pytest.mark.timeout(400),
    pytest.mark.skipif(not available(), reason="needs root, iproute2 and the right to add a network namespace"),
]


@pytest.fixture
def hosts() -> Iterator[Hosts]:
    h = Hosts(["learner", "a1", "a2"])
    try:
        h.up()
        yield h
    finally:
        h.down()


def test_a_job_across_four_namespaces_survives_a_10s_link_cut(tmp_path: Path, hosts: Hosts) -> None:
    job_args = ["--env", "referential", "--steps", str(STEPS), "--num-envs", "32", "--hp", "hidden=64",
                "--hp", "learning_starts=256", "--eval-episodes", "100", "--log-every", "2000"]  # fmt: skip
    job = MultiHostJob(hosts, "mh", job_args, tmp_path, ["a1", "a2"])
    try:
        job.start()
        assert job.learner is not None
        t_end = time.monotonic() + 120
        while not job.rows() or job.rows()[-1]["env_steps"] < 6_000:
            assert job.learner.poll() is None, job.log("learner")[-3000:]
            assert time.monotonic() < t_end, "no progress before the cut"
            time.sleep(0.5)
        before = job.rows()[-1]["env_steps"]
        hosts.cut("a1", down=True)
        time.sleep(10.0)
        hosts.cut("a1", down=False)
        restored = time.time()
        assert job.learner.wait(240) == 0, job.log("learner")[-3000:]
    finally:
        job.stop()
    summary = json.loads((job.out / "summary.json").read_text())
    print(f"cut at {before:,} env steps; finished at {summary['env_steps']:,}")
    # the right count: the job's steps, past them by less than one chunk per actor (JobConfig.steps), and only once
    overshoot = 2 * 32 * RuntimeConfig().publish_steps  # 2 actor hosts × num_envs × steps per chunk
    assert STEPS <= summary["env_steps"] < STEPS + overshoot and summary["updates"] > 0
    steps = [r["env_steps"] for r in job.rows()]
    assert steps == sorted(steps) and steps[-1] >= STEPS  # one learner, counting on: nothing it took was lost
    assert "restart" not in job.log("learner").lower(), job.log("learner")[-3000:]
    assert "crashed" not in job.log("a1"), job.log("a1")[-3000:]
    after = {key for t, key in job.heard() if t > restored + 1.0}
    assert any("a1-host" in key for key in after), sorted(after)  # the cut host's actor delivers again
    assert any("a2-host" in key for key in after), sorted(after)
