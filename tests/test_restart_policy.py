"""The supervisor's restart policy per role, on fake processes: churn is respawned at once and never fails a job,
a crash loop backs off, and the budgets a failure names can be set from the CLI and REST."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from convoy.config import job_config
from convoy.protocol.session import ZenohSettings
from convoy.services.procs import SHORT_LIFE_S, ProcessGroup, Slot


class FakeProc:
    """What ProcessGroup reads of a multiprocessing.Process."""

    pid = None

    def __init__(self) -> None:
        self.exitcode: int | None = None

    def join(self, timeout: float | None = None) -> None:
        pass

    def is_alive(self) -> bool:
        return self.exitcode is None

    def terminate(self) -> None:
        self.exitcode = -15


def actor_group(monkeypatch: pytest.MonkeyPatch, **runtime: object) -> ProcessGroup:
    job = job_config(algo="idqn", env="referential", steps=1000, runtime={"actors": 2, **runtime})
    group = ProcessGroup("policy", job, "unused", ZenohSettings(), roles=("actor",))
    monkeypatch.setattr(group, "_spawn_actor", lambda index, generation: Slot("actor", index, generation, FakeProc()))
    group.scale_actors(2)
    return group


def kill(group: ProcessGroup, index: int, lived_s: float) -> None:
    slot = group.actors[index]
    slot.started = time.monotonic() - lived_s
    slot.proc.exitcode = -9


def test_churn_is_respawned_at_once_and_never_fails_the_job(monkeypatch: pytest.MonkeyPatch) -> None:
    group = actor_group(monkeypatch)
    for death in range(40):  # 40 deaths in well under a minute, each actor having run a while
        kill(group, death % 2, lived_s=SHORT_LIFE_S + 5)
        events = group.poll()
        assert [e.kind for e in events] == ["crashed", "respawned"], events
    assert group.failed is None and len(group.actors) == 2


def test_a_crash_loop_backs_off_doubling(monkeypatch: pytest.MonkeyPatch) -> None:
    group = actor_group(monkeypatch, restart_backoff_s=0.05)
    delays = []
    for _ in range(3):
        kill(group, 0, lived_s=0.1)
        events = group.poll()
        assert [e.kind for e in events] == ["crashed", "backoff"], events
        assert 0 not in group.actors  # not yet respawned
        delays.append(group.respawn_at[0][0] - time.monotonic())
        time.sleep(delays[-1] + 0.01)
        assert [e.kind for e in group.poll()] == ["respawned"]
    assert delays[0] < delays[1] < delays[2] and delays[2] == pytest.approx(0.2, abs=0.02)
    kill(group, 0, lived_s=SHORT_LIFE_S + 1)  # it ran long enough: the streak is over, back at once
    assert [e.kind for e in group.poll()] == ["crashed", "respawned"]


def test_the_actor_budget_names_the_field_and_how_to_set_it(monkeypatch: pytest.MonkeyPatch) -> None:
    group = actor_group(monkeypatch, actor_max_restarts=3)
    for death in range(3):
        kill(group, death % 2, lived_s=SHORT_LIFE_S + 5)
        assert group.poll()[-1].kind == "respawned"
    kill(group, 1, lived_s=SHORT_LIFE_S + 5)
    failed = group.poll()[-1]
    assert failed.kind == "failed" and "actor crashed 4 times" in failed.detail
    assert "runtime.actor_max_restarts" in failed.detail and "--runtime actor_max_restarts=N" in failed.detail


def test_runtime_settings_come_from_the_cli_and_the_rest_body() -> None:
    from convoy.api.models import JobSubmit
    from convoy.cli.jobs import submit_body
    from convoy.cli.main import build_parser
    from convoy.cli.train import job_from_args
    from convoy.config import ConfigError

    args = build_parser().parse_args(["train", "--runtime", "actor_max_restarts=500", "--runtime", "max_restarts=9"])
    job = job_from_args(args)
    assert (job.runtime.actor_max_restarts, job.runtime.max_restarts) == (500, 9)
    args = build_parser().parse_args(["jobs", "submit", "--runtime", "actor_max_restarts=500"])
    body = submit_body(args)
    assert body["runtime"] == {"actor_max_restarts": 500}
    assert JobSubmit(**body).job_config().runtime.actor_max_restarts == 500
    with pytest.raises(ConfigError) as info:
        JobSubmit(runtime={"zenoh": {"mode": "router"}}).job_config()
    assert info.value.field == "runtime.zenoh"
    with pytest.raises(ConfigError) as info:
        JobSubmit(runtime={"max_restarts": -1}).job_config()
    assert info.value.field == "runtime.max_restarts"


def test_a_diverged_learner_fails_the_job_at_once_with_the_fix(monkeypatch: pytest.MonkeyPatch) -> None:
    """Non-finite losses in a row are deterministic: the learner exits DIVERGED and is not restarted (a restart from
    its checkpoint would diverge the same way); the failure says what to change."""
    from convoy.protocol.exitcodes import DIVERGED

    job = job_config(algo="idqn", env="referential", steps=1000, runtime={"actors": 1})
    group = ProcessGroup("diverge", job, "unused", ZenohSettings(), roles=("learner",))
    spawned: list[int] = []

    def spawn(generation: int) -> Slot:
        spawned.append(generation)
        return Slot("learner", 0, generation, FakeProc())

    monkeypatch.setattr(group, "_spawn_learner", spawn)
    group.start_learner()
    assert group.learner is not None
    group.learner.proc.exitcode = DIVERGED
    events = group.poll()
    assert events[-1].kind == "failed" and "diverged" in events[-1].detail and "lr" in events[-1].detail, events
    assert spawned == [0] and group.poll() == []


def test_the_learner_process_reports_divergence_by_its_exit_code(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    from convoy.learner import service
    from convoy.protocol.exitcodes import DIVERGED

    def diverge(self: service.Learner) -> int:
        raise FloatingPointError("idqn: 100 updates in a row had a non-finite loss (nan)")

    monkeypatch.setattr(service.Learner, "run", diverge)
    monkeypatch.setattr(service.signal, "signal", lambda *a: None)
    job = job_config(algo="idqn", env="referential", steps=1000)
    assert service.run_learner("diverge", job, "unused", ZenohSettings()) == DIVERGED
    assert "training diverged: idqn: 100 updates in a row" in caplog.text


def test_the_learner_tells_its_supervisor_the_job_has_its_data_before_it_tells_the_actors() -> None:
    """The budget that completes the job (actors leave on it) goes out as the last chunk is credited, before its
    updates, the end-of-run curve point and checkpoint, which take seconds on a loaded machine: the supervisor's
    word (``ProcessGroup.has_data``) comes first, so the actors' exits are never judged before it."""
    from convoy.learner.service import Learner
    from convoy.protocol import wire

    said: list[str] = []

    class Publisher:
        def put(self, payload: bytes) -> None:
            said.append(f"budget {wire.decode(payload).body['ingested_steps']}")

    job = job_config(algo="idqn", env="referential", steps=1000)
    learner = Learner("order", job, "unused", ZenohSettings(), on_data=lambda: said.append("has data"))
    learner.pub_budget = Publisher()
    learner._publish_budget(1064, 936, 3)
    learner._publish_budget(1128, 1000, 4)  # the chunk that completes the job
    learner._publish_budget(1000, 1000, 9)  # the loop's last word
    assert said == ["budget 936", "has data", "budget 1000", "has data", "budget 1000"]


@pytest.mark.parametrize("role", ["actor", "learner"])
def test_a_process_that_refuses_the_jobs_configuration_fails_the_job_at_once(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, role: str
) -> None:
    """A process that died on a ConfigError (a CoDBC teacher that is gone or refused) was respawned with back-off
    for ever: the job read "running" with no error. Its exit code CONFIG fails the job at once, not respawned, with
    the refusal the process reported as the reason."""
    from convoy.protocol.exitcodes import CONFIG
    from convoy.protocol.reports import REPORTS_FILE, Report, append

    job = job_config(algo="idqn", env="referential", steps=1000, runtime={"actors": 2})
    group = ProcessGroup("refuse", job, str(tmp_path), ZenohSettings(), roles=(role,))
    spawned: list[tuple[int, int]] = []

    def spawn_actor(index: int, generation: int) -> Slot:
        spawned.append((index, generation))
        return Slot("actor", index, generation, FakeProc())

    def spawn_learner(generation: int) -> Slot:
        spawned.append((0, generation))
        return Slot("learner", 0, generation, FakeProc())

    monkeypatch.setattr(group, "_spawn_actor", spawn_actor)
    monkeypatch.setattr(group, "_spawn_learner", spawn_learner)
    if role == "actor":
        group.scale_actors(2)
        slot = group.actors[1]
    else:
        group.start_learner()
        assert group.learner is not None
        slot = group.learner
    said = "ConfigError: teacher: checkpoint t.pt: refused — it holds Python objects"
    append(tmp_path / REPORTS_FILE, Report("error", "actor-0", "ConfigError: another process's word"))
    append(tmp_path / REPORTS_FILE, Report("error", slot.ident, said))
    before = list(spawned)
    slot.proc.exitcode = CONFIG
    events = group.poll()
    failed = events[-1]
    assert failed.kind == "failed" and failed.refused and failed.ident == slot.ident, events
    assert f"{slot.ident} refused the job's configuration (exit code {CONFIG})" in failed.detail
    assert said in failed.detail and "another process" not in failed.detail, failed.detail
    assert group.failed == failed.detail and spawned == before  # nothing respawned
    assert group.poll() == []


def test_a_role_process_exits_config_on_a_config_error_and_reports_it(tmp_path: Path) -> None:
    """What tells the supervisor: a ConfigError in a role process is its exit code CONFIG, and its message is the
    process's last word in the job's reports (where the job's error comes from)."""
    import logging

    from convoy.config import ConfigError
    from convoy.protocol.exitcodes import CONFIG
    from convoy.protocol.reports import REPORTS_FILE, read
    from convoy.services.procs import _role_main

    def refuse() -> int:
        raise ConfigError("teacher", "checkpoint t.pt: no such file")

    root = logging.getLogger("convoy")
    handlers = list(root.handlers)
    try:
        with pytest.raises(SystemExit) as exit_:
            _role_main("h.actor-0", str(tmp_path / REPORTS_FILE), refuse)
    finally:
        for handler in list(root.handlers):
            root.removeHandler(handler)
        for handler in handlers:
            root.addHandler(handler)
    assert exit_.value.code == CONFIG
    (report,) = read(tmp_path / REPORTS_FILE)
    assert (report.kind, report.source) == ("error", "h.actor-0")
    assert report.detail == "ConfigError: teacher: checkpoint t.pt: no such file"
