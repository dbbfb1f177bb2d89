"""The job service end to end: a real ``convoy serve`` on 127.0.0.1, real job processes, httpx as the client.

* lifecycle: submit a small job, watch it run, scale 1 → 2 actors and see the alive count follow, stop it, resume
  it with another actor count and a larger budget, watch it complete, fetch its checkpoint, evaluate it;
* restart: SIGKILL the API during a job; a new API on the same data finds the job, with its full metric history
  (no gaps or duplicates), and the job keeps running to completion.
"""

from __future__ import annotations

import io
import itertools
import json
import math
import os
import re
import signal
import time
import zipfile
from pathlib import Path
from typing import Any

import pytest

from tests.busy import busy_cores
from tests.doc_output import compare, output_blocks
from tests.pace import paced
from tests.service_fixture import AUTH, SMALL_JOB, Service

pytestmark = pytest.mark.timeout(300)


def submit(svc: Service, **extra: object) -> str:
    resp = svc.client.post("/jobs", json={**SMALL_JOB, **extra}, headers=AUTH)
    assert resp.status_code == 201, resp.text
    body = resp.json()
    assert body["state"] == "queued" and body["queue_position"] is not None
    return body["id"]


def steps_of(svc: Service, job_id: str) -> list[int]:
    rows = svc.client.get(f"/jobs/{job_id}/metrics", params={"names": "return"}).json()["rows"]
    return [r["env_steps"] for r in rows]


def test_submit_scale_stop_resume_and_fetch_a_checkpoint(tmp_path: Path) -> None:
    svc = Service(tmp_path / "svc").start()
    try:
        job = submit(svc, steps=2_000_000, actors=1)
        svc.wait(job, lambda v: v["state"] == "running" and v["actors_alive"] == 1, what="running with 1 actor")
        svc.wait(job, lambda v: v["progress"]["env_steps"] > 3000, what="metrics flowing")

        resp = svc.client.patch(f"/jobs/{job}", json={"actors": 2}, headers=AUTH)
        assert resp.status_code == 200 and resp.json()["actors"] == 2
        svc.wait(job, lambda v: v["actors_alive"] == 2, what="a second actor alive")
        svc.wait(job, lambda v: v["last_checkpoint"] is not None, what="a checkpoint")

        assert svc.client.post(f"/jobs/{job}/stop", headers=AUTH).json()["state"] == "stopping"
        stopped = svc.wait(job, lambda v: v["state"] == "stopped", what="stopped")
        at_stop = stopped["progress"]["env_steps"]
        assert 0 < at_stop < 2_000_000

        resp = svc.client.post(f"/jobs/{job}/resume", json={"actors": 1, "steps": at_stop + 20_000}, headers=AUTH)
        assert resp.status_code == 200 and resp.json()["state"] == "queued" and resp.json()["actors"] == 1
        done = svc.wait(job, lambda v: v["state"] in ("completed", "failed"), timeout=120, what="completed")
        assert done["state"] == "completed", done["error"]
        assert done["progress"]["env_steps"] >= at_stop + 20_000
        final = done["final"]  # the job's greedy evaluation beside the references, as its summary.json has it
        assert math.isfinite(final["eval_return"]) and final["eval_ci95"] >= 0 and "random" in final["references"]
        log = (svc.data.parent / f"serve-{svc.port}.log").read_text()  # convoy serve says what its jobs do
        for said in (
            f"job {job}: submitted",
            f"job {job}: queued → starting",
            f"job {job}: running → stopping",
            f"job {job}: stopped → queued (resume requested)",
            "→ completed (the learner has all its steps)",
        ):
            assert said in log, (said, log[-2000:])

        steps = steps_of(svc, job)
        assert steps == sorted(set(steps)), "metric history has duplicates or is out of order"
        assert steps[-1] >= at_stop + 20_000

        listing = svc.client.get(f"/jobs/{job}/checkpoints").json()["checkpoints"]
        assert [c["name"] for c in listing] == ["best.pt", "checkpoint.pt"]  # the last and the best greedy point
        blob = svc.client.get(f"/jobs/{job}/checkpoints/checkpoint.pt")
        assert blob.status_code == 200 and zipfile.is_zipfile(io.BytesIO(blob.content))  # a torch.save archive

        t0 = time.monotonic()  # an evaluation answers at once and runs in its own process
        ev = svc.client.post(f"/jobs/{job}/evaluate", json={"episodes": 8, "checkpoint": "best.pt"}, headers=AUTH)
        assert ev.status_code == 202 and ev.json()["state"] == "running" and time.monotonic() - t0 < 5, ev.text
        url = f"/jobs/{job}/evaluations/{ev.json()['id']}"
        done = svc.wait_for(url, lambda v: v["state"] != "running", what="the evaluation")
        assert done["state"] == "completed" and done["result"]["episodes"] == 8, done
        assert done["result"]["checkpoint"].endswith("best.pt") and done["request"]["checkpoint"] == "best.pt"
        assert svc.client.get(f"/jobs/{job}/evaluations").json()["evaluations"] == [done]
        assert svc.client.get(f"/jobs/{job}/evaluations/abcdef").status_code == 404

        assert svc.client.get("/jobs", params={"state": "completed"}).json()["jobs"][0]["id"] == job
        output = svc.client.get(f"/jobs/{job}/logs", params={"lines": 50}).json()["lines"]
        assert any("exited learner" in line for line in output), output  # the host's log, its last lines
        assert 'convoy_jobs{state="completed"} 1.0' in svc.client.get("/metrics").text
    finally:
        svc.stop()


SCALE_BOUND_S = 30.0  # the most a PATCH to more actors may take to show them alive, on a loaded machine too


@pytest.mark.timeout(600)
def test_live_scaling_brings_new_actors_up_within_a_bound_on_a_loaded_machine(tmp_path: Path) -> None:
    """Both cores busy with other work the whole time, so the job's host takes seconds to start. A PATCH to 2 actors
    while the job is starting (its host not yet listening for commands: the service tells it once its liveliness
    token shows it can hear) shows 2 actors alive within ``SCALE_BOUND_S`` of the job running; a PATCH to 3 while
    it runs shows 3 within ``SCALE_BOUND_S`` of the PATCH. Getting the job started is not what is bounded, nor how
    fast scaling is on an idle machine."""
    with busy_cores():
        svc = Service(tmp_path / "svc")
        try:
            svc.start(timeout=240)
            job = submit(svc, steps=2_000_000, actors=1)
            svc.wait(job, lambda v: v["state"] == "starting", 120, "starting", every=0.01)
            resp = svc.client.patch(f"/jobs/{job}", json={"actors": 2}, headers=AUTH)
            assert resp.status_code == 200 and resp.json()["actors"] == 2, resp.text
            svc.wait(job, lambda v: v["state"] == "running", 240, "running", every=0.1)
            t0 = time.monotonic()
            svc.wait(
                job,
                lambda v: v["actors_alive"] == 2,
                SCALE_BOUND_S,
                "2 actors alive (asked while starting)",
                0.1,
                pace=False,
            )
            print(f"2 actors alive {time.monotonic() - t0:.1f} s after the job ran (PATCHed while starting)")

            t0 = time.monotonic()
            resp = svc.client.patch(f"/jobs/{job}", json={"actors": 3}, headers=AUTH)
            assert resp.status_code == 200 and resp.json()["actors"] == 3, resp.text
            view = svc.wait(job, lambda v: v["actors_alive"] == 3, SCALE_BOUND_S, "3 actors alive", 0.1, pace=False)
            print(f"3 actors alive {time.monotonic() - t0:.1f} s after the PATCH while running, both cores busy")
            assert view["state"] == "running" and view["actors"] == 3, view
        finally:
            svc.stop()


def test_a_stop_while_the_job_is_starting_takes_effect_at_once(tmp_path: Path) -> None:
    """The job's host may not be subscribed to its commands yet: the stop must not wait for the grace kill."""
    from convoy.services.jobservice import STOP_GRACE_S

    svc = Service(tmp_path / "svc").start()
    try:
        job = submit(svc, steps=2_000_000, actors=1)
        svc.wait(job, lambda v: v["state"] == "starting", what="starting", every=0.01)
        t0 = time.monotonic()
        assert svc.client.post(f"/jobs/{job}/stop", headers=AUTH).json()["state"] == "stopping"
        svc.wait(job, lambda v: v["state"] == "stopped", timeout=STOP_GRACE_S / 2, what="stopped")
        print(f"stopped {time.monotonic() - t0:.2f} s after the stop, asked while starting")
    finally:
        svc.stop()


def test_drops_show_by_role_and_reason_in_the_jobs_status_and_prometheus(tmp_path: Path) -> None:
    """A process holding the job's credential (a buggy or compromised insider) sends garbage and well-formed
    chunks with impossible values: the job runs on, and ``GET /jobs/{id}`` and ``/metrics`` count them by role
    (learner, actors, service) and reason while it runs."""
    import zenoh

    from convoy.config import job_config
    from convoy.protocol import keys, wire
    from convoy.protocol.session import ZenohSettings, open_session, read_credentials
    from convoy.services.jobservice import CREDENTIALS_FILE
    from tests.test_runtime import hostile_chunks, wait_for

    data = tmp_path / "svc"
    svc = Service(data).start()
    try:
        job = submit(svc, steps=2_000_000, actors=1)
        view = svc.wait(job, lambda v: v["progress"]["env_steps"] > 1000, what="metrics flowing")
        assert view["progress"]["dropped"]["learner"] == {}, view["progress"]
        config = svc.client.get(f"/jobs/{job}").json()["config"]
        user, password = read_credentials(data / "jobs" / job / CREDENTIALS_FILE)
        endpoint = json.loads((data / "jobs" / job / "job.json").read_text())["runtime"]["zenoh"]["connect"][0]
        session = open_session(ZenohSettings(mode="client", connect=(endpoint,), user=user, password=password))
        try:
            block = zenoh.CongestionControl.BLOCK
            chunks = session.declare_publisher(keys.exp(job, "insider"), congestion_control=block)
            weights = session.declare_publisher(keys.weights(job), congestion_control=block)
            metrics = session.declare_publisher(keys.metrics(job, "learner", "0"), congestion_control=block)
            for pub in (chunks, weights, metrics):

                def matched(p: Any = pub) -> bool:  # zenoh's stub says matching_status is a bool: it is a struct
                    return bool(p.matching_status.matching)

                wait_for(matched, 10, "the insider to reach the job")
            for _reason, body in hostile_chunks(job_config(**config)) * 3:
                chunks.put(wire.encode("chunk", body, "insider"))
            for i in range(50):
                weights.put(bytes([i]) * 7)
                metrics.put(b"\x93\x01\x02\x03")
        finally:
            session.close()

        def counted(v: dict) -> bool:
            dropped = v["progress"]["dropped"]
            return (
                dropped["learner"].get("action-range", 0) >= 3
                and dropped["learner"].get("non-finite", 0) >= 6
                and dropped["actors"]["garbage"] >= 50
                and sum(dropped["service"].values()) >= 50
            )

        view = svc.wait(job, counted, timeout=60, what="the drops in the job's status")
        assert view["state"] == "running" and view["actors_alive"] == 1, view
        text = svc.client.get("/metrics").text
        assert f'convoy_job_dropped_messages{{job="{job}",reason="action-range",role="learner"}}' in text, text
        assert f'convoy_job_dropped_messages{{job="{job}",reason="garbage",role="actors"}}' in text
    finally:
        svc.stop()


def test_a_failed_jobs_status_carries_the_cause_from_its_process_log(tmp_path: Path) -> None:
    """A real failure: the learner gives up waiting for data at once (data_timeout_s 0.01 s, no restart allowed;
    the actor's first chunk is 4,096 steps × the job's envs away, so no machine is fast enough to beat the timeout).
    The job's error is not only "learner crashed 1 times": it carries the cause the learner reported."""
    svc = Service(tmp_path / "svc").start()
    try:
        runtime = {"max_restarts": 0, "data_timeout_s": 0.01, "publish_steps": 4096}
        job = submit(svc, steps=100_000, actors=1, runtime=runtime)
        view = svc.wait(job, lambda v: v["state"] in ("failed", "completed"), timeout=120, what="the job to end")
        assert view["state"] == "failed", view
        assert (
            "learner crashed 1 times" in view["error"] and "cause: learner-0: no chunk from any actor" in view["error"]
        )
        assert "raise runtime.data_timeout_s" in view["error"] and f"convoy jobs logs {job}" in view["error"]
        lines = svc.client.get(f"/jobs/{job}/logs", params={"lines": 50}).json()["lines"]
        assert any(line.startswith("[learner-0] no chunk from any actor") for line in lines), lines
    finally:
        svc.stop()


def test_a_job_whose_processes_refuse_its_configuration_fails_with_the_refusal(tmp_path: Path) -> None:
    """A CoDBC job whose teacher was fine when submitted and corrupt when its processes load it: its actor dies on
    a ConfigError. It was respawned with back-off for ever (state running, error null); now the job fails at once
    with the refusal as its error. The job waits behind a blocker while the file goes bad, so nothing races."""
    from convoy.algos.agent import make_agent
    from convoy.algos.checkpoint import save_checkpoint
    from convoy.config import job_config
    from convoy.envs import make_batched

    teacher = tmp_path / "teacher.pt"
    config = job_config(
        algo="ma-mesn", env="treadmill", env_params=SMALL_JOB["env_params"], algo_params={"hidden": [8]}
    )
    env = make_batched("treadmill", 1, **SMALL_JOB["env_params"])
    save_checkpoint(teacher, make_agent(config, env.spec, device="cpu"), config, {"env_steps": 0})
    env.close()
    svc = Service(tmp_path / "svc", max_processes=3).start()
    try:
        blocker = submit(svc, steps=2_000_000, actors=1)
        svc.wait(blocker, lambda v: v["state"] in ("starting", "running"), what="the blocker to start")
        job = submit(svc, algo="codbc", steps=100_000, actors=1, algo_params={"hidden": [32], "teacher": str(teacher)})
        assert svc.client.get(f"/jobs/{job}").json()["state"] == "queued"
        teacher.write_bytes(b"not a checkpoint any more")
        assert svc.client.delete(f"/jobs/{blocker}", headers=AUTH).status_code == 204  # now the job starts
        t0 = time.monotonic()
        view = svc.wait(job, lambda v: v["state"] in ("failed", "completed"), timeout=120, what="the job to end")
        assert view["state"] == "failed", view
        assert time.monotonic() - t0 < paced(30), "a refused job should fail within seconds of its processes starting"
        assert "refused the job's configuration" in view["error"], view["error"]
        assert "ConfigError: teacher:" in view["error"] and "corrupt or not a Convoy checkpoint" in view["error"]
    finally:
        svc.stop()


def test_a_killed_api_finds_its_running_job_again_with_its_full_history(tmp_path: Path) -> None:
    data = tmp_path / "svc"
    svc = Service(data).start()
    again: Service | None = None
    try:
        job = submit(svc, steps=120_000, actors=1)
        svc.wait(job, lambda v: v["progress"]["env_steps"] >= 8000, what="some progress")
        before = steps_of(svc, job)
        svc.kill()  # SIGKILL: no chance to clean up
        # the job trains on without the API: its learner keeps writing rows to the job's metrics file (or, on a
        # fast machine, finishes the job: its summary appears)
        rows, summary = data / "jobs" / job / "metrics.jsonl", data / "jobs" / job / "summary.json"
        lines = len(rows.read_text().splitlines())
        t_end = time.monotonic() + 60
        while len(rows.read_text().splitlines()) < lines + 2 and not summary.is_file():
            assert time.monotonic() < t_end, "the job stopped training while the API was down"
            time.sleep(0.2)

        again = Service(data, port=svc.port).start()
        view = again.client.get(f"/jobs/{job}").json()
        assert view["state"] in ("running", "completed"), view
        after = steps_of(again, job)
        assert after[: len(before)] == before  # nothing lost
        # the new API follows the job on (new rows reach it) and commands it: a stop ends it. Not its completion:
        # how long 120 k steps take is the machine's business
        beyond = after[-1] + 2 * SMALL_JOB["log_every"]
        again.wait(
            job, lambda v: v["progress"]["env_steps"] >= beyond or v["state"] == "completed", timeout=120,
            what="progress seen by the restarted API",
        )  # fmt: skip
        if again.client.get(f"/jobs/{job}").json()["state"] == "running":
            assert again.client.post(f"/jobs/{job}/stop", headers=AUTH).status_code == 200
        end = again.wait(job, lambda v: v["state"] in ("stopped", "completed", "failed"), timeout=120, what="the end")
        assert end["state"] in ("stopped", "completed"), end
        final = steps_of(again, job)
        assert final == sorted(set(final)) and final[-1] >= beyond
        gaps = [b - a for a, b in itertools.pairwise(final) if b - a > 2 * SMALL_JOB["log_every"]]
        assert not gaps, f"metric history has gaps: {gaps}"
    finally:
        if again is not None:
            again.stop()
        svc.stop()


def test_jobs_beyond_the_process_budget_wait_in_a_queue(tmp_path: Path) -> None:
    svc = Service(tmp_path / "svc", max_processes=5).start()  # room for one job with 1 actor (3 processes)
    try:
        first = submit(svc, steps=20_000, actors=1)
        second = submit(svc, steps=20_000, actors=1)
        svc.wait(first, lambda v: v["state"] == "running", what="the first job running")
        waiting = svc.client.get(f"/jobs/{second}").json()
        assert waiting["state"] == "queued" and waiting["queue_position"] == 1
        too_big = svc.client.post("/jobs", json={**SMALL_JOB, "steps": 1000, "actors": 4}, headers=AUTH)
        assert too_big.status_code == 422 and too_big.json()["field"] == "actors"  # could never fit
        svc.wait(first, lambda v: v["state"] == "completed", timeout=120, what="the first job completed")
        svc.wait(second, lambda v: v["state"] in ("running", "completed"), timeout=60, what="the second job started")
        svc.wait(second, lambda v: v["state"] == "completed", timeout=120, what="the second job completed")
    finally:
        svc.stop()


def test_a_process_without_the_jobs_credential_cannot_command_it(tmp_path: Path) -> None:
    """Zenoh refuses the transport of a peer that cannot authenticate as the job (no credential, or the job's user
    with a wrong password): its forged "scale to 1" reaches nobody, where before it took a job from 2 actors to 1
    without the API's token."""

    import zenoh

    from convoy.protocol import keys, wire
    from convoy.protocol.session import ZenohSettings, open_session
    from convoy.services.jobservice import host_name

    data = tmp_path / "svc"
    svc = Service(data).start()
    try:
        job = submit(svc, steps=2_000_000, actors=2)
        svc.wait(job, lambda v: v["state"] == "running" and v["actors_alive"] == 2, what="running with 2 actors")
        config = json.loads((data / "jobs" / job / "job.json").read_text())
        zenoh_cfg = config["runtime"]["zenoh"]
        assert "password" not in zenoh_cfg  # the password reaches the host through its environment only
        endpoint = zenoh_cfg["connect"][0]
        forged = wire.encode("command", {"op": "scale", "args": {"actors": 1}}, "intruder")
        outsiders = [ZenohSettings(connect=(endpoint,)), ZenohSettings(connect=(endpoint,), user=job, password="x")]
        for settings in outsiders:
            session = open_session(settings)
            try:
                pub = session.declare_publisher(
                    keys.host(host_name(job), "cmd"), congestion_control=zenoh.CongestionControl.BLOCK
                )
                time.sleep(2.0)
                assert not pub.matching_status.matching  # no subscriber of the job is reachable
                for _ in range(3):
                    pub.put(forged)
            finally:
                session.close()
        time.sleep(3.0)
        view = svc.client.get(f"/jobs/{job}").json()
        assert view["actors"] == 2 and view["actors_alive"] == 2, view
    finally:
        svc.stop()


def role_pids(host_pid: int) -> list[int]:
    """The job's learner and actors: forkserver children in the host's process group."""
    procs: dict[int, tuple[int, int, str]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text().rsplit(")", 1)[1].split()
                cmd = (entry / "cmdline").read_bytes().decode(errors="replace")
            except OSError:
                continue
            procs[int(entry.name)] = (int(stat[1]), int(stat[2]), cmd)  # ppid, pgid, command line
    forked = [p for p, (ppid, pgid, cmd) in procs.items() if pgid == host_pid and "forkserver" in cmd]
    return [p for p in forked if "forkserver" in procs.get(procs[p][0], (0, 0, ""))[2]]


def test_the_service_log_tells_of_a_crash_and_the_respawn(tmp_path: Path) -> None:
    svc = Service(tmp_path / "svc").start()
    try:
        job = submit(svc, steps=2_000_000, actors=1)
        view = svc.wait(job, lambda v: v["state"] == "running" and v["actors_alive"] == 1, what="running")
        roles = role_pids(int(svc.host_pids()[0]))
        assert len(roles) == 2, roles  # the learner and one actor
        os.kill(max(roles), signal.SIGKILL)
        log = tmp_path / f"serve-{svc.port}.log"
        t_end = time.monotonic() + 60
        while not re.search(rf"job {job}: respawned h-{job}\.", log.read_text()):
            assert time.monotonic() < t_end, log.read_text()
            time.sleep(0.3)
        text = log.read_text()
        assert re.search(rf"\d\d:\d\d:\d\d job {job}: crashed h-{job}\.\w+-\d+ exit code -9", text), text
        shown = next(b for b in output_blocks() if b.doc == "service.md" and not b.command)  # the guide's excerpt
        problems = compare(shown.output, text, None, [(r"actor-@", None)])  # by template: times, ids, delays aside
        assert not problems, "docs/service.md's log excerpt:\n" + "\n".join(problems) + "\n\nlogged:\n" + text
        assert view["state"] == "running"
        assert svc.client.patch(f"/jobs/{job}", json={"actors": 2}, headers=AUTH).status_code == 200
        assert svc.client.delete(f"/jobs/{job}", headers=AUTH).status_code == 204
        text = log.read_text()  # every change a user asks for is in the log, not only the ones the service makes
        assert f"job {job}: scaled to 2 actors" in text and f"job {job}: deleted (running before" in text, text
    finally:
        svc.stop()


def test_a_finished_evaluation_is_reaped_and_a_failed_one_says_so(tmp_path: Path) -> None:
    """An evaluation whose process ended without a result reads as failed with its reason (an unreaped child is a
    zombie whose pid looks alive: it would read as running for ever), and its process is collected."""
    import sys

    from convoy.api.models import EvalRequest
    from convoy.services import evaluations

    (tmp_path / "checkpoint.pt").write_bytes(b"not a checkpoint")
    started = evaluations.start(tmp_path, "job", EvalRequest(episodes=2), 0, sys.executable)
    t_end = time.monotonic() + 120
    while (view := evaluations.find(tmp_path, "job", started["id"]))["state"] == "running":
        assert time.monotonic() < t_end, view
        time.sleep(0.2)
    assert view["state"] == "failed" and "corrupt or not a Convoy checkpoint" in view["error"], view
    assert not evaluations._CHILDREN  # reaped
