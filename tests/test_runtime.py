"""The distributed runtime end to end: real actor and learner processes talking over Zenoh on 127.0.0.1.

Every test starts its own processes (forks of the runner's forkserver), on free ports, and stops them by PID in a
``finally``; none depends on another's state. Sizes are CI-sized: referential game or a small treadmill with small
networks.
"""

from __future__ import annotations

import collections
import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from convoy.algos.algorithm import epsilon_at
from convoy.algos.checkpoint import read_checkpoint
from convoy.config import JobConfig, job_config
from convoy.protocol import keys
from convoy.protocol.session import ZenohSettings, free_port, loopback, open_session
from convoy.services.jobrunner import AliveSet, JobRunner
from convoy.services.procs import ProcessGroup, Slot
from convoy.services.training import run_inprocess
from convoy.transition import from_columns
from tests.busy import busy_cores
from tests.pace import paced
from tests.proctree import descendants

REFERENTIAL: dict[str, Any] = {
    "env": "referential",
    "num_envs": 32,
    "log_every": 1000,
    "eval_episodes": 200,
    "algo_params": {"hidden": [64], "learning_starts": 256},
}
TREADMILL: dict[str, Any] = {
    "env": "treadmill",
    "num_envs": 16,
    "log_every": 1000,
    "eval_episodes": 0,
    "env_params": {"length": 30, "width": 12},
    "algo_params": {"hidden": [32, 12], "learning_starts": 256, "replay_ratio": 0.25},
}


def group_of(runner: JobRunner) -> ProcessGroup:
    """The runner's processes (there once it has started them)."""
    assert runner.group is not None, "the runner has not started its processes"
    return runner.group


def learner_of(runner: JobRunner) -> Slot:
    """The runner's learner process (there but while it is being restarted)."""
    slot = group_of(runner).learner
    assert slot is not None, "no learner right now"
    return slot


def alive_of(runner: JobRunner) -> AliveSet:
    """The runner's view of the liveliness tokens (there once it has started)."""
    assert runner.alive is not None, "the runner has not started"
    return runner.alive


def wait_for(cond: Callable[[], bool], timeout: float, what: str, every: float = 0.02) -> float:
    """Seconds until ``cond()`` held; fails the test naming ``what`` after ``timeout`` (the reference machine's
    seconds: ``tests/pace.py``)."""
    timeout = paced(timeout)
    t0 = time.monotonic()
    while not cond():
        if time.monotonic() - t0 > timeout:
            pytest.fail(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(every)
    return time.monotonic() - t0


class Background:
    """A JobRunner in a thread; ``result`` / ``error`` once it returns; processes stopped by PID at the end."""

    def __init__(self, runner: JobRunner) -> None:
        self.runner = runner
        self.result: dict[str, Any] | None = None
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        try:
            self.result = self.runner.run()
        except BaseException as exc:  # reported by join()
            self.error = exc

    def __enter__(self) -> Background:
        self.thread.start()
        assert self.runner.started.wait(60), "runner did not start its processes"
        return self

    def join(self, timeout: float = 900) -> dict[str, Any]:
        """The job's summary once it ends; ``timeout`` only stops a hang (a loaded 2-core machine took > 120 s
        for a 4 k-step job with a respawn)."""
        self.thread.join(timeout)
        assert not self.thread.is_alive(), f"job did not finish within {timeout:g} s"
        if self.error:
            raise self.error
        assert self.result is not None
        return self.result

    def __exit__(self, *exc: object) -> None:
        self.runner.stop()  # the runner stops its processes (SIGTERM, then SIGKILL by PID) and returns
        self.thread.join(60)
        group = self.runner.group
        if self.thread.is_alive() and group is not None:  # belt and braces: never leave a process behind
            for pid in group.pids().values():
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
            self.thread.join(30)
        assert not self.thread.is_alive(), "the job runner did not stop"


def test_distributed_learner_matches_inprocess_on_referential(tmp_path: Path) -> None:
    """Equivalence: 1 actor + the learner over Zenoh reach the success the in-process trainer reaches.

    30 k steps: every seed 0-7 reaches 1.0 both ways; at 12 k most seeds stop at 0.72-0.8 in either runtime, so a
    shorter run tests the seed and the CPU's rounding, not the runtime.
    """
    job = job_config(algo="ma-mesn", steps=30_000, seed=0, runtime={"actors": 1}, **REFERENTIAL)
    inproc = run_inprocess(job, tmp_path / "inproc", progress=False).as_dict()
    runner = JobRunner("equiv", job, tmp_path / "dist", progress=False)
    dist = runner.run()
    assert not [e for e in runner.events if e.kind in ("crashed", "respawned")], runner.events  # a normal end
    assert inproc["eval_return"] >= 0.9, inproc
    assert dist["eval_return"] >= 0.9, dist
    assert abs(dist["eval_return"] - inproc["eval_return"]) <= 0.1
    # the same samples-per-insert ratio: updates follow the data in both
    assert dist["updates"] == pytest.approx(inproc["updates"] * dist["env_steps"] / inproc["env_steps"], rel=0.1)
    assert dist["dropped"] == 0


@pytest.mark.parametrize("slack", [None, 1])
def test_dial_runs_distributed_with_chunks_of_its_unroll(tmp_path: Path, slack: int | None) -> None:
    """DIAL's chunk is its unroll (32 steps × 32 envs here), longer than the default slack of 2 × 8-step chunks
    implies: the flow control must let one whole chunk through, with the default slack and with a tiny one."""
    runtime = {"actors": 1, "slack_steps": slack}
    job = job_config(algo="dial", steps=4_000, seed=0, runtime=runtime, **{**REFERENTIAL, "eval_episodes": 0})
    assert job.runtime.slack(job.num_envs, job.runtime.chunk_len(32)) >= 32 * job.num_envs
    runner = JobRunner("dial", job, tmp_path / "dial", progress=False)
    with Background(runner) as bg:
        result = bg.join()
    assert result["env_steps"] >= 4_000 and result["updates"] > 0, result
    assert not [e for e in runner.events if e.kind in ("crashed", "respawned")], runner.events  # a normal end


def test_killed_actor_is_respawned_and_the_job_completes(tmp_path: Path) -> None:
    """A SIGKILLed actor is replaced (a new generation, its liveliness token up) and the job completes. How fast is
    a benchmark's figure (``benchmarks/faults.py``: under 2 s on an idle machine), not this test's: a loaded
    machine may take longer."""
    job = job_config(algo="idqn", steps=200_000, seed=1, runtime={"actors": 2}, **TREADMILL)
    runner = JobRunner("killactor", job, tmp_path, progress=False)
    with Background(runner) as bg:
        wait_for(lambda: runner.alive is not None and runner.alive.count("actor") == 2, 60, "2 actors alive")
        time.sleep(2.0)  # mid-job
        victim = group_of(runner).actors[0]
        # actors yield to the learner on shared cores (runtime.actor_nice, default 5)
        assert os.getpriority(os.PRIO_PROCESS, victim.proc.pid) == min(19, os.getpriority(os.PRIO_PROCESS, 0) + 5)
        os.kill(victim.proc.pid, signal.SIGKILL)
        killed_at = time.monotonic()
        respawn_s = wait_for(
            lambda: 0 in group_of(runner).actors and group_of(runner).actors[0].generation == 1,
            60,
            "the actor's respawn",
        )
        assert group_of(runner).actors[0].proc.is_alive()
        wait_for(lambda: "actor-0.1" in alive_of(runner).ids("actor"), 30, "the respawned actor's liveliness token")
        token_s = time.monotonic() - killed_at
        summary = bg.join()
    print(f"respawned {respawn_s:.2f} s after kill -9; its liveliness token {token_s:.2f} s after")
    assert summary["env_steps"] >= job.steps
    kinds = [(e.kind, e.ident) for e in runner.events]
    assert ("crashed", "actor-0") in kinds and ("respawned", "actor-0.1") in kinds


def shm_mappings(pid: int) -> set[str]:
    """The shared-memory files a process has mapped (Zenoh's segments live under /dev/shm)."""
    with open(f"/proc/{pid}/maps") as fh:
        return {line.split()[-1] for line in fh if "/dev/shm/" in line}


@pytest.mark.skipif(not Path("/proc/self/maps").exists(), reason="needs /proc (Linux)")
def test_actor_churn_does_not_grow_the_learners_shared_memory_nor_fail_the_job(tmp_path: Path) -> None:
    """Every dead actor's segments stayed mapped in the learner (~20 MiB each); churn must not grow its memory.
    The count is read after a first death (a process may map a segment or two more once it has run a while,
    e.g. the learner's own publisher) and again after 7 more: it must not grow with the deaths. The default
    restart policy once failed a job at the 6th actor death within its window while the learner was healthy;
    the window is an hour here, so all 8 deaths fall in it whatever the machine's speed. (The kills come seconds
    apart, which the policy reads as a crash loop and slows by restart_backoff_s, doubling; tests/
    test_restart_policy.py tests that, so it is 0 here.)"""
    runtime = {"actors": 1, "restart_window_s": 3600.0, "restart_backoff_s": 0.0}  # actor_max_restarts: default
    job = job_config(algo="idqn", steps=10_000_000, seed=3, runtime=runtime, **TREADMILL)
    runner = JobRunner("churn", job, tmp_path, progress=False)
    counts = []
    with Background(runner):
        wait_for(lambda: runner.last_row.get("env_steps", 0) > 0, 60, "learning to start")
        learner = learner_of(runner).proc.pid
        for kill in range(8):
            steps = runner.last_row.get("env_steps", 0)
            os.kill(group_of(runner).actors[0].proc.pid, signal.SIGKILL)
            back = lambda k=kill: 0 in group_of(runner).actors and group_of(runner).actors[0].generation == k + 1  # noqa: E731
            wait_for(back, 30, "the respawn")

            def fed(s: float = steps) -> bool:
                return runner.last_row.get("env_steps", 0) > s + 2000

            wait_for(fed, 60, "the new actor's data")
            counts.append(shm_mappings(learner))
        assert not [e for e in runner.events if e.kind == "failed"], runner.events
    print(f"learner's shared-memory mappings after each of 8 actor deaths: {[len(c) for c in counts]}")
    assert len(counts[-1]) <= len(counts[0]), sorted(counts[-1] - counts[0])


def test_killed_learner_resumes_from_its_checkpoint(tmp_path: Path) -> None:
    every = 4_000
    job = job_config(algo="idqn", steps=60_000, seed=2, checkpoint_every=every, runtime={"actors": 1}, **TREADMILL)
    cfg = job.algo_config()
    per_interval = every * cfg.replay_ratio / cfg.batch_size  # updates between two checkpoints
    runner = JobRunner("killlearner", job, tmp_path, progress=False)
    with Background(runner) as bg:
        wait_for(lambda: (tmp_path / "checkpoint.pt").is_file() and runner.last_row.get("env_steps", 0) > 2 * every,
                 90, "a checkpoint and two intervals of progress")  # fmt: skip
        before = runner.last_row["updates"]
        os.kill(learner_of(runner).proc.pid, signal.SIGKILL)
        wait_for(lambda: (slot := group_of(runner).learner) is not None and slot.generation == 1, 60, "restart")
        summary = bg.join(180)
    rows = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    steps = [r["env_steps"] for r in rows]
    assert steps == sorted(steps) and len(steps) == len(set(steps)), "metric history has duplicates after restart"
    assert len(runner.resumes) == 1
    resumed = runner.resumes[0]["resumed_updates"]
    print(f"updates before kill -9: {before:.0f}; the restarted learner resumed at {resumed:.0f}")
    assert before - per_interval - 1 <= resumed <= before + per_interval + 1  # back at most one checkpoint interval
    # with its replay buffer as it was at that checkpoint, not empty (each env step is one joint row)
    resumed_steps = runner.resumes[0]["resumed_env_steps"]
    assert runner.resumes[0]["resumed_replay_rows"] == min(resumed_steps, cfg.replay_capacity) > 0
    assert summary["env_steps"] >= job.steps
    kinds = [(e.kind, e.role) for e in runner.events]
    assert ("crashed", "learner") in kinds and ("respawned", "learner") in kinds
    # the schedules go on from the checkpoint's counters: ε of every row is the schedule's at its step
    for r in rows:
        assert r["epsilon"] == pytest.approx(epsilon_at(cfg, r["env_steps"], job.steps), abs=1e-6), r
    before_kill = [r["return"] for r in rows if r["env_steps"] <= resumed_steps][-3:]
    after = [r["return"] for r in rows if r["env_steps"] > resumed_steps][:3]
    print(f"ε-greedy training return, last 3 rows before the resume point {before_kill}, first 3 after {after}")


def test_actor_count_scales_live_and_every_actor_delivers(tmp_path: Path) -> None:
    """1 → 3 → 1 actors while the job runs, the learner untouched; every live actor reports its rate. How the
    throughput follows is measured by benchmarks/runtime.py (~1.5× with 3 actors on 2 cores), not asserted here:
    it depends on what else the machine runs."""
    values = {**TREADMILL, "algo_params": {**TREADMILL["algo_params"], "replay_ratio": 0.02}}
    job = job_config(algo="idqn", steps=10**8, seed=3, runtime={"actors": 1}, **values)
    runner = JobRunner("scale", job, tmp_path, progress=False)

    def rates(ids: int) -> list[float]:
        wait_for(lambda: alive_of(runner).count("actor") == ids, 60, f"{ids} actors alive")
        live = alive_of(runner).ids("actor")

        def delivering() -> bool:  # a new actor's first report may come before its first chunk got through
            reports = runner.reports.actors
            return live <= set(reports) and all(reports[i]["env_steps_per_s"] > 0 for i in live)

        wait_for(delivering, 60, f"steps from all {ids} live actors")
        return [runner.reports.actors[i]["env_steps_per_s"] for i in live]

    with Background(runner):
        one = rates(1)
        runner.scale(3)
        three = rates(3)
        runner.scale(1)
        back = rates(1)
        learner_pid = learner_of(runner).proc.pid
        assert learner_of(runner).generation == 0  # scaling never restarted the learner
    print(f"env-steps/s: 1 actor {sum(one):,.0f} → 3 actors {sum(three):,.0f} → 1 actor {sum(back):,.0f} "
          f"(learner pid {learner_pid})")  # fmt: skip
    assert len(one) == 1 and len(three) == 3 and len(back) == 1
    assert all(r > 0 for r in [*one, *three, *back])


HOSTILE_REPEATS = 20


def test_garbage_on_the_jobs_keys_is_dropped_and_counted(tmp_path: Path) -> None:
    import zenoh

    from convoy.protocol import wire

    job = job_config(algo="idqn", steps=40_000, seed=4, runtime={"actors": 1}, **TREADMILL)
    runner = JobRunner("garbage", job, tmp_path, progress=False)
    rng = np.random.default_rng(0)
    valid = wire.encode("budget", {"allowed_steps": 1, "ingested_steps": 0, "version": 0}, "x")
    with Background(runner) as bg:
        wait_for(lambda: runner.alive is not None and runner.alive.count("actor") == 1, 60, "the actor")
        wait_for(lambda: runner.last_row.get("env_steps", 0) > 0, 60, "learning to start")
        settings = group_of(runner).settings  # a peer of the job's network
        session = open_session(settings)
        try:
            block = zenoh.CongestionControl.BLOCK
            targets = [keys.exp("garbage", "intruder"), keys.weights("garbage"), keys.ctl("garbage", "budget")]
            targets.append(keys.metrics("garbage", "actor", "intruder"))
            pubs = [session.declare_publisher(k, congestion_control=block) for k in targets]
            wait_for(lambda: all(p.matching_status.matching for p in pubs), 10, "the job's subscribers to match")
            sent = [0, 0, 0, 0]
            for i in range(10_000):
                kind = i % 4
                choice = (i // 4) % 4
                if choice == 0:
                    payload = rng.bytes(int(rng.integers(0, 300)))
                elif choice == 1:
                    payload = valid[: int(rng.integers(0, len(valid)))]
                elif choice == 2:
                    payload = b"\x81\xa1v\x07"  # {"v": 7}: a foreign schema version
                else:
                    payload = b"\x93\x01\x02\x03"  # a msgpack list
                pubs[kind].put(payload)
                sent[kind] += 1
            hostile = hostile_chunks(job)  # well-formed chunks of this job's schema with impossible values
            for _ in range(HOSTILE_REPEATS):  # the audit: 30 bad actions crashed a learner, 20 NaN chunks poisoned one
                for _reason, body in hostile:
                    pubs[0].put(wire.encode("chunk", body, "intruder"))
            # a well-formed metrics message without the fields a learner row carries: the supervisor ignores it
            metrics_pub = session.declare_publisher(keys.metrics("garbage", "learner", "0"))
            wait_for(lambda: metrics_pub.matching_status.matching, 10, "the supervisor's metrics subscriber")
            metrics_pub.put(wire.encode("metrics", wire.metrics_body("learner", "0", {"return": 1.0}), "intruder"))
        finally:
            session.close()

        def actor_drops() -> float:
            return max((m.get("dropped", 0) for m in runner.reports.actors.values()), default=0)

        # the actor reports drops in its metrics, about once a second
        wait_for(lambda: actor_drops() >= sent[1] + sent[2] - 5, 60, "the actor's drop counts")
        summary = bg.join()
    assert not [e for e in runner.events if e.kind in ("crashed", "failed")], runner.events
    assert summary["env_steps"] >= job.steps
    assert summary["dropped"] >= sent[0]  # every garbage chunk was counted, none inserted
    assert actor_drops() >= sent[1] + sent[2] - 5  # weights + budget garbage: the actor counted them
    expected = collections.Counter(reason for reason, _ in hostile)
    for reason, n in expected.items():  # each well-formed hostile chunk was refused for its reason, none inserted
        assert summary["dropped_by_reason"].get(reason, 0) >= n * HOSTILE_REPEATS, summary["dropped_by_reason"]
    assert runner.reports.bad >= 1
    elsewhere = summary["dropped_elsewhere"]  # the job's summary also counts what actors and the supervisor dropped
    assert elsewhere["actors"]["garbage"] >= sent[1] + sent[2] - 5
    assert sum(elsewhere["supervisor"].values()) >= sent[3] + 1
    state = read_checkpoint(tmp_path / "checkpoint.pt")["state"]
    tensors = [t for t in _tensors(state) if t.is_floating_point()]
    assert tensors and all(bool(torch.isfinite(t).all()) for t in tensors)


def test_actors_told_to_leave_by_a_peer_are_respawned_and_the_job_finishes(tmp_path: Path) -> None:
    """Forged stop commands and a forged final budget make actors exit 0; the supervisor takes that as leaving
    early (its learner has not reported the job's steps), respawns them and the job completes."""
    import zenoh

    from convoy.protocol import wire

    job = job_config(algo="idqn", steps=30_000, seed=5, runtime={"actors": 2}, **TREADMILL)
    runner = JobRunner("forged", job, tmp_path, progress=False)
    with Background(runner) as bg:
        wait_for(lambda: runner.alive is not None and runner.alive.count("actor") == 2, 60, "the actors")
        wait_for(lambda: runner.last_row.get("env_steps", 0) > 0, 60, "learning to start")
        session = open_session(group_of(runner).settings)
        try:
            block = zenoh.CongestionControl.BLOCK
            stop = session.declare_publisher(keys.ctl("forged", "stop"), congestion_control=block)
            budget = session.declare_publisher(keys.ctl("forged", "budget"), congestion_control=block)
            wait_for(lambda: stop.matching_status.matching and budget.matching_status.matching, 10, "the actors")
            for _ in range(3):
                stop.put(wire.encode("command", {"op": "stop", "args": {}}, "intruder"))
            forged = {"allowed_steps": job.steps, "ingested_steps": job.steps, "version": 0}
            wait_for(lambda: alive_of(runner).count("actor") == 2, 30, "the actors to be back after the stops")
            for _ in range(3):
                budget.put(wire.encode("budget", forged, "intruder"))
        finally:
            session.close()
        summary = bg.join(180)
    left = [e for e in runner.events if e.kind == "crashed" and "before the learner" in e.detail]
    assert len(left) >= 2, runner.events  # both actors left on the forged stops and came back
    assert not [e for e in runner.events if e.kind == "failed"], runner.events
    assert summary["env_steps"] >= job.steps


def test_a_peer_without_the_jobs_credential_cannot_reach_it(tmp_path: Path) -> None:
    """A local run roots its network with a fresh per-job credential: a peer on the root's port without it (or with
    the job's user and a wrong password) matches none of the job's subscribers, and its stop commands reach no
    actor; the job's own processes hold the credential in a private 0600 file."""
    import stat

    import zenoh

    from convoy.protocol import wire
    from convoy.protocol.session import ZenohSettings

    job = job_config(algo="idqn", steps=20_000, seed=6, runtime={"actors": 1}, **TREADMILL)
    runner = JobRunner("locked", job, tmp_path, progress=False)
    with Background(runner) as bg:
        wait_for(lambda: runner.alive is not None and runner.alive.count("actor") == 1, 60, "the actor")
        member = group_of(runner).settings
        assert member.user == "locked" and member.password is not None and member.credentials_file is not None
        assert stat.S_IMODE(Path(member.credentials_file).stat().st_mode) == 0o600
        root = member.connect[0]
        for outsider in (ZenohSettings(connect=(root,)), ZenohSettings(connect=(root,), user="locked", password="x")):
            session = open_session(outsider)
            try:
                stop = session.declare_publisher(
                    keys.ctl("locked", "stop"), congestion_control=zenoh.CongestionControl.BLOCK
                )
                time.sleep(2.0)
                assert not stop.matching_status.matching
                for _ in range(3):
                    stop.put(wire.encode("command", {"op": "stop", "args": {}}, "intruder"))
            finally:
                session.close()
        summary = bg.join(180)
    assert not [e for e in runner.events if e.kind in ("crashed", "failed")], runner.events  # no actor left
    assert summary["env_steps"] >= job.steps
    assert not Path(member.credentials_file).exists()  # removed with the run


def _tensors(x: object) -> list[torch.Tensor]:
    """Every tensor inside a nested checkpoint state."""
    if isinstance(x, torch.Tensor):
        return [x]
    if isinstance(x, dict):
        return [t for v in x.values() for t in _tensors(v)]
    if isinstance(x, list | tuple):
        return [t for v in x for t in _tensors(v)]
    return []


def hostile_chunks(job: JobConfig) -> list[tuple[str, dict]]:
    """(drop reason, a chunk body) that has this job's fields, dtypes and shapes but values no env can produce."""
    from convoy.algos.agent import make_agent
    from convoy.envs import make_batched
    from convoy.learner.service import transition_schema
    from convoy.protocol import wire

    env = make_batched(job.env, 1, **job.env_params)
    schema = transition_schema(job, make_agent(job, env.spec))
    env.close()

    def chunk(**change: float) -> dict:
        arrays = {k: np.zeros((1, 2, *shape), dtype=np.dtype(dtype)) for k, (dtype, shape) in schema.items()}
        for name, value in change.items():
            arrays[name][...] = value
        return wire.chunk_body(from_columns(arrays), "intruder", policy_version=0, env_steps=2, returns=[])

    nan, inf = float("nan"), float("inf")
    return [("action-range", chunk(action=99)), ("non-finite", chunk(reward=nan)), ("non-finite", chunk(obs=inf))]


def test_router_topology_as_local_processes(tmp_path: Path) -> None:
    """Multi-host shape: a router, a learner host and an actor host, connected only through the router's TCP
    endpoint (client mode, no shared memory)."""
    port = free_port()
    endpoint = loopback(port)
    flags = "--job-id mh --env referential --steps 12000 --num-envs 32 --hp hidden=64 --hp learning_starts=256"
    job_flags = [*flags.split(), "--eval-episodes", "200", "--log-every", "2000"]
    net = ["--mode", "client", "--connect", endpoint, "--no-shm"]
    cmd = [sys.executable, "-m", "convoy.cli"]
    procs: list[subprocess.Popen] = []
    logs = tmp_path / "logs"
    logs.mkdir()

    def start(name: str, args: list[str]) -> subprocess.Popen:
        fh = open(logs / f"{name}.log", "w")  # noqa: SIM115 (closed with the process)
        p = subprocess.Popen([*cmd, *args], stdout=fh, stderr=subprocess.STDOUT, cwd=Path(__file__).parents[1])
        procs.append(p)
        return p

    try:
        start("router", ["router", "--listen", endpoint])
        learner = start("learner", ["host", "--name", "learner-host", "--roles", "learner", "--out",
                                    str(tmp_path / "run"), *job_flags, *net])  # fmt: skip
        actor_args = ["host", "--name", "actor-host", "--roles", "actor", "--actors", "2", *job_flags, *net]
        actors = start("actors", actor_args)
        assert learner.wait(180) == 0, (logs / "learner.log").read_text()
        assert actors.wait(60) == 0, (logs / "actors.log").read_text()
    finally:
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for p in procs:
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(5)
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["env_steps"] >= 12000 and summary["updates"] > 0
    assert summary["eval_return"] > summary["random_return"]
    # no session listened on loopback but the router: the others were clients
    assert ZenohSettings(mode="client", connect=(endpoint,)).mode == "client"


def test_a_learner_that_keeps_crashing_fails_the_job_with_the_reason(tmp_path: Path) -> None:
    import torch

    from convoy.services.procs import JobFailed

    if torch.cuda.is_available():
        pytest.skip("needs a machine without CUDA (the learner must crash on device=cuda)")
    job = job_config(algo="idqn", steps=10_000, device="cuda", runtime={"actors": 1, "max_restarts": 1}, **TREADMILL)
    runner = JobRunner("crashloop", job, tmp_path, progress=False)
    t0 = time.monotonic()
    with pytest.raises(
        JobFailed,
        match=r"learner crashed 2 times .* raise runtime.max_restarts \(convoy train --runtime max_restarts=N"
        r".*or fix the cause",
    ):
        runner.run()
    assert time.monotonic() - t0 < 60
    assert runner.group is not None and not runner.group.pids()  # every process stopped


def test_a_process_that_refuses_the_jobs_configuration_fails_the_job_with_the_refusal(tmp_path: Path) -> None:
    """A CoDBC job whose teacher file turns out corrupt where its processes run (it was fine, or not there, when the
    job was checked): the actor that loads it refuses it, and the job fails with that refusal — not respawned with
    back-off for ever. Real processes; the bound is generous for a loaded 2-core machine."""
    from convoy.services.procs import JobRefused

    teacher = tmp_path / "teacher.pt"
    teacher.write_bytes(b"not a checkpoint")
    algo_params = {**REFERENTIAL["algo_params"], "teacher": str(teacher)}
    job = job_config(algo="codbc", steps=20_000, runtime={"actors": 1}, **{**REFERENTIAL, "algo_params": algo_params})
    runner = JobRunner("refused", job, tmp_path / "run", progress=False)
    with Background(runner) as bg, pytest.raises(JobRefused) as info:
        bg.join(90)
    text = str(info.value)
    assert "refused the job's configuration" in text and "ConfigError: teacher:" in text, text
    assert "corrupt or not a Convoy checkpoint" in text, text
    assert not [e for e in runner.events if e.kind == "respawned"], runner.events
    assert runner.group is not None and not runner.group.pids()  # every process stopped


def _alive(pid: int) -> bool:
    """Running, not a zombie (``services.jobservice.pid_alive``'s signal 0 would count an unreaped exit as alive)."""
    with contextlib.suppress(OSError):
        return Path(f"/proc/{pid}/stat").read_text().split(") ")[1][0] not in "ZX"
    return False


def _describe(pids: list[int]) -> str:
    """Each PID's command line, state and kernel wait channel, per thread."""
    out = []
    for pid in pids:
        with contextlib.suppress(OSError):
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")[:200]
            state = Path(f"/proc/{pid}/stat").read_text().split(") ")[1][0]
            waits = sorted({(t / "wchan").read_text() for t in Path(f"/proc/{pid}/task").iterdir()})
            out.append(f"{pid} [{state}] {cmd} waits in {waits}")
    return "; ".join(out)


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads the process tree from /proc")
def test_roles_exit_when_the_runner_is_killed(tmp_path: Path) -> None:
    """kill -9 of `convoy train`: its learner and actors (forks of its forkserver, which their open descriptors
    keep alive) notice their supervisor is gone and exit, and the forkserver with them — nothing runs on."""
    cfg = tmp_path / "job.json"
    cfg.write_text(json.dumps({"algo": "idqn", "steps": 10_000_000, "runtime": {"actors": 2}, **TREADMILL}))
    cmd = [sys.executable, "-m", "convoy.cli", "train", "--config", str(cfg), "--out", str(tmp_path / "run")]
    with open(tmp_path / "train.log", "w") as log:
        proc = subprocess.Popen([*cmd, "--no-progress"], stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        wait_for(lambda: (tmp_path / "run" / "metrics.jsonl").is_file(), 60, "the job's first metric row", every=0.2)
        roles = descendants(proc.pid)
        assert len(roles) >= 4, roles  # forkserver, learner, 2 actors (+ resource tracker)
        proc.kill()
        proc.wait(5)
        # they notice within a second and exit after their last checkpoint; on a loaded 2-core machine that once
        # took over 60 s, so the bound is generous: the test is that they go, not how fast
        t0 = time.monotonic()
        while any(_alive(p) for p in roles) and time.monotonic() - t0 < 240:
            time.sleep(0.1)
        lingering = [p for p in roles if _alive(p)]
        if lingering:  # say which and where they wait: SIGUSR1 makes a role print its threads' stacks to the log
            for pid in lingering:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGUSR1)
            time.sleep(2)
            pytest.fail(f"still running 240 s after kill -9 of the runner: {_describe(lingering)}\n"
                        f"{(tmp_path / 'train.log').read_text()[-20_000:]}")  # fmt: skip
        print(f"{len(roles)} processes gone {time.monotonic() - t0:.2f} s after kill -9 of the runner")
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)  # the whole session, by its leader's PID
        proc.wait(5)


def test_a_learner_without_data_gives_up_with_the_reason(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """No actor ever sends a chunk: the learner checkpoints and exits NO_DATA after runtime.data_timeout_s."""
    from convoy.learner.service import Learner
    from convoy.protocol.exitcodes import NO_DATA

    job = job_config(algo="idqn", steps=10_000, runtime={"actors": 1, "data_timeout_s": 1.0}, **TREADMILL)
    code = Learner("nodata", job, tmp_path, ZenohSettings()).run()
    assert code == NO_DATA
    assert (tmp_path / "checkpoint.pt").is_file()
    assert "no chunk from any actor for 1 s" in caplog.text


def test_a_distributed_population_writes_each_run_and_resumes_every_run_after_a_killed_learner(
    tmp_path: Path,
) -> None:
    """``seeds``: the actors step every run's envs and act with the stacked policy (weights as one message), the
    learner updates all runs at once and writes DIR/seed-N per run; a learner killed with SIGKILL comes back with
    every run's checkpoint and the population's replay, and each run's folder reads as a single run's."""
    from convoy.algos.checkpoint import load_checkpoint

    every, seeds = 4_000, [3, 5, 8]
    job = job_config(algo="idqn", steps=24_000, seeds=seeds, checkpoint_every=every, runtime={"actors": 1}, **TREADMILL)
    runner = JobRunner("killpop", job, tmp_path, progress=False)
    dirs = [tmp_path / f"seed-{s}" for s in seeds]
    with Background(runner) as bg:
        wait_for(lambda: all((d / "checkpoint.pt").is_file() for d in dirs) and (tmp_path / "replay.npz").is_file()
                 and runner.last_row.get("env_steps", 0) > 2 * every, 120, "checkpoints of every run")  # fmt: skip
        os.kill(learner_of(runner).proc.pid, signal.SIGKILL)
        wait_for(lambda: (slot := group_of(runner).learner) is not None and slot.generation == 1, 60, "restart")
        result = bg.join(240)
    assert len(runner.resumes) == 1 and runner.resumes[0]["resumed_replay_rows"] > 0, runner.resumes
    resumed_steps = runner.resumes[0]["resumed_env_steps"]
    assert len(result["runs"]) == len(seeds)
    for s, d, summary in zip(seeds, dirs, result["runs"], strict=True):
        assert {"checkpoint.pt", "summary.json", "metrics.jsonl", "curve.png"} <= {p.name for p in d.iterdir()}
        assert summary["env_steps"] >= job.steps and summary["updates"] > 0 and summary["episodes"] > 0, summary
        rows = [json.loads(line) for line in (d / "metrics.jsonl").read_text().splitlines()]
        steps = [r["env_steps"] for r in rows]
        assert steps == sorted(steps) and len(steps) == len(set(steps)), f"seed {s}: duplicate rows after restart"
        assert any(r["env_steps"] <= resumed_steps for r in rows) and rows[-1]["env_steps"] >= job.steps
        agent, run_job, counters = load_checkpoint(d / "checkpoint.pt", device="cpu")  # a plain single run
        assert run_job.seed == s and not run_job.seeds and getattr(agent, "runs", None) == 1
        assert counters["env_steps"] == summary["env_steps"]
    weights = [read_checkpoint(d / "checkpoint.pt")["state"]["online"] for d in dirs]
    first = next(iter(weights[0]))
    assert not torch.equal(weights[0][first], weights[1][first]), "runs of different seeds hold the same weights"


def test_an_orphaned_worker_that_hangs_while_closing_is_made_to_exit_with_its_stacks(tmp_path: Path) -> None:
    """ParentWatch arms a C-level timer when the parent goes: a worker stuck after that (here: asleep for ever)
    prints its threads' stacks and exits instead of running on."""
    child = (
        "import time\n"
        "from convoy.protocol.exitcodes import ParentWatch\n"
        "watch = ParentWatch(exit_after_s=1.0)\n"
        "print('watching', flush=True)\n"
        "while not watch.orphaned():\n"
        "    time.sleep(0.05)\n"
        "time.sleep(1000)  # a close that never returns\n"
    )
    parent = (
        "import subprocess, sys\n"
        f"p = subprocess.Popen([sys.executable, '-c', {child!r}], stdout=subprocess.PIPE, stderr=sys.stderr)\n"
        "print(p.pid, flush=True)\n"
        "p.stdout.readline()\n"  # the child watches: the parent may go
    )
    log = tmp_path / "child.log"
    with open(log, "w") as err:
        out = subprocess.run([sys.executable, "-c", parent], stdout=subprocess.PIPE, stderr=err, text=True, timeout=120)
    pid = int(out.stdout.split()[0])
    try:
        wait_for(lambda: not _alive(pid), 120, "the orphaned child to exit", every=0.1)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    text = log.read_text()
    assert "Timeout" in text and "most recent call first" in text and "<module>" in text, text


def test_opening_a_session_gives_up_when_told_while_zenoh_open_hangs(monkeypatch: pytest.MonkeyPatch) -> None:
    """A role forked just before its supervisor died was seen blocked in zenoh.open for minutes: with give_up the
    caller gets SessionAbandoned (and exits) while the open still hangs; errors of the open reach the caller."""
    import zenoh

    from convoy.protocol.session import SessionAbandoned, open_session

    release = threading.Event()
    monkeypatch.setattr(zenoh, "open", lambda conf: release.wait(60))
    checks: list[float] = []
    with pytest.raises(SessionAbandoned):

        def give_up() -> bool:
            checks.append(time.monotonic())
            return len(checks) >= 3

        open_session(ZenohSettings(), give_up=give_up)
    assert len(checks) == 3  # polled while the open hung, until it said so
    release.set()

    def refuse(conf: object) -> None:
        raise zenoh.ZError("bad endpoint")

    monkeypatch.setattr(zenoh, "open", refuse)
    with pytest.raises(zenoh.ZError, match="bad endpoint"):
        open_session(ZenohSettings(), give_up=lambda: False)


@pytest.mark.timeout(600)
def test_a_normal_end_on_a_loaded_machine_is_no_crash(tmp_path: Path) -> None:
    """Both cores busy: ``convoy train --algo ma-mesn --actors 4 --steps 3000`` (a small treadmill) logs no crash and
    no respawn. The actors leave when the learner's last budget says the job has its data, long before its final
    evaluation and last row; the learner told its group first (``ProcessGroup.has_data``), so no exit is taken for a
    crash. What the user reads is checked: the ``[kind] id`` lines the command prints for its processes' events."""
    config = tmp_path / "job.json"
    config.write_text(json.dumps({**TREADMILL, "eval_episodes": 64}))
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "convoy.cli", "train", "--config", str(config), "--algo", "ma-mesn", "--actors", "4",
           "--steps", "3000", "--seed", "2", "--no-progress", "--out", str(out)]  # fmt: skip
    log = tmp_path / "train.log"
    with busy_cores(), log.open("wb") as sink:
        # its own process group: the command's learner and actors (forks of its forkserver) end with it, by its PID
        proc = subprocess.Popen(cmd, stdout=sink, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            code = proc.wait(540)
        finally:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(30)
    text = log.read_text(errors="replace")
    assert code == 0, text[-4000:]
    events = re.findall(r"^\[(\w+)\] (\S+)", text, flags=re.MULTILINE)
    assert not [e for e in events if e[0] in ("crashed", "respawned", "backoff", "failed")], text[-4000:]
    assert len({ident for kind, ident in events if kind == "exited" and ident.startswith("actor-")}) == 4, text[-4000:]
    assert ("exited", "learner-0") in events, text[-4000:]
    assert json.loads((out / "summary.json").read_text())["env_steps"] >= 3000


def test_a_distributed_learner_starts_from_its_demonstrator(tmp_path: Path) -> None:
    """``demonstrator``: the learner process clones the planner before it takes a chunk (its actors act with the
    clone from the first weights it broadcasts) and writes each run's ``demonstration.json``; the job then trains
    to its steps as any other."""
    demo = {"demonstrator": "private-planner", "demo_rounds": 1, "demo_episodes": 2, "demo_epochs": 1,
            "hidden": [32], "learning_starts": 200}  # fmt: skip
    job = job_config(algo="idqn", steps=1_000, seeds=[0, 1], runtime={"actors": 1},
                     **{**TREADMILL, "algo_params": demo})  # fmt: skip
    runner = JobRunner("demo", job, tmp_path, progress=False)
    result = runner.run()
    assert not [e for e in runner.events if e.kind in ("crashed", "respawned")], runner.events
    assert len(result["runs"]) == 2
    for seed, summary in zip((0, 1), result["runs"], strict=True):
        figures = json.loads((tmp_path / f"seed-{seed}" / "demonstration.json").read_text())
        assert figures["demonstrator"] == "private-planner" and figures["demo_env_steps"] > 0
        assert summary["env_steps"] >= job.steps and summary["wall_s"] > summary["clone_s"] == figures["demo_s"] > 0
