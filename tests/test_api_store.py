"""The job service's SQLite store (``services/store.py``): jobs and their lifecycle, metric history and polling without
duplicates or gaps, persistence across reopen, schema-version refusal, and concurrent writers with a poller."""

from __future__ import annotations

import math
import sqlite3
import threading
from pathlib import Path

import pytest

from convoy.api.lifecycle import (
    ACTIVE_STATES,
    ALLOWED_TRANSITIONS,
    FINAL_STATES,
    InvalidTransition,
    JobRecord,
    JobState,
    StoreError,
    UnknownJob,
)
from convoy.services.store import SCHEMA_VERSION, JobStore

CONFIG = {"algo": "ma_mesn", "env": {"name": "treadmill", "lanes": 3}, "lr": 3e-4}


@pytest.fixture
def store(tmp_path: Path):
    with JobStore(tmp_path / "db" / "jobs.sqlite") as s:
        yield s


def rows(steps, **extra) -> list[dict]:
    return [{"env_steps": s, "return": s / 10, "loss": 1.0 / (s + 1), **extra} for s in steps]


# -- jobs --------------------------------------------------------------------------------------------------------------


def test_states_and_table_are_consistent() -> None:
    assert {s.value for s in JobState} == {
        "queued",
        "starting",
        "running",
        "stopping",
        "stopped",
        "completed",
        "failed",
    }
    assert set(JobState) == ACTIVE_STATES | FINAL_STATES
    assert not ACTIVE_STATES & FINAL_STATES
    assert set(ALLOWED_TRANSITIONS) == set(JobState)
    assert JobState.running == "running" and str(JobState.running) == "running"
    for final in FINAL_STATES:
        assert ALLOWED_TRANSITIONS[final] == {JobState.queued}  # every final state can be resumed


def test_create_get_list_filter(store: JobStore, tmp_path: Path) -> None:
    assert (tmp_path / "db").is_dir()  # parent directories are created
    a = store.create("a", CONFIG, actors=4, out_dir="runs/a")
    b = store.create("b", {"algo": "ppo"}, actors=2)
    c = store.create("c", {}, actors=1, state=JobState.running)

    assert isinstance(a, JobRecord)
    assert a.state is JobState.queued and a.config == CONFIG and a.actors == 4 and a.out_dir == "runs/a"
    assert a.error is None and a.last_checkpoint is None and a.progress == {}
    assert a.created_at == a.updated_at > 0
    assert store.get("a") == a
    assert store.exists("b") and not store.exists("zzz")

    assert [j.id for j in store.list()] == ["a", "b", "c"]
    assert [j.id for j in store.list(JobState.queued)] == ["a", "b"]
    assert [j.id for j in store.list("running")] == ["c"]
    assert store.list(JobState.failed) == []

    d = a.as_dict()
    assert d["state"] == "queued" and d["id"] == "a" and d["config"] == CONFIG and d["progress"] == {}
    assert set(d) == {
        "id",
        "state",
        "config",
        "actors",
        "created_at",
        "updated_at",
        "out_dir",
        "error",
        "last_checkpoint",
        "progress",
    }
    assert b.as_dict()["out_dir"] is None and c.state is JobState.running


def test_duplicate_and_unknown_ids(store: JobStore) -> None:
    store.create("dup", CONFIG, actors=1)
    with pytest.raises(StoreError, match="'dup' already exists"):
        store.create("dup", {}, actors=1)
    assert store.get("dup").config == CONFIG  # the failed create changed nothing

    for call in (
        lambda: store.get("ghost"),
        lambda: store.transition("ghost", "starting"),
        lambda: store.transitions("ghost"),
        lambda: store.update("ghost", actors=3),
        lambda: store.append_metrics("ghost", rows([1])),
        lambda: store.metrics("ghost"),
        lambda: store.cut_metrics("ghost", 0),
        lambda: store.last_step("ghost"),
        lambda: store.queue_position("ghost"),
        lambda: store.delete("ghost"),
    ):
        with pytest.raises(UnknownJob, match=r"job 'ghost' not found$") as info:
            call()
        assert info.value.job_id == "ghost"
        assert isinstance(info.value, StoreError) and isinstance(info.value, ValueError)


def test_bad_arguments(store: JobStore) -> None:
    with pytest.raises(StoreError, match="unknown job state 'bogus'; valid states: queued, starting, running"):
        store.list("bogus")
    with pytest.raises(StoreError, match="non-empty str"):
        store.create("", {}, actors=1)
    with pytest.raises(StoreError, match="actors must be"):
        store.create("x", {}, actors=-1)
    with pytest.raises(StoreError, match="config must be a dict"):
        store.create("x", [1, 2], actors=1)  # type: ignore[arg-type]  # a config that is no dict, on purpose
    with pytest.raises(StoreError, match="cannot be stored as JSON"):
        store.create("x", {"f": object()}, actors=1)
    assert not store.exists("x")


def test_transitions_allowed_refused_and_history(store: JobStore) -> None:
    store.create("j", CONFIG, actors=2)
    assert store.transition("j", JobState.starting, "scheduled").state is JobState.starting
    assert store.transition("j", "running").state is JobState.running

    with pytest.raises(InvalidTransition) as info:
        store.transition("j", JobState.queued)
    msg = str(info.value)
    assert "'j'" in msg and "is running" in msg and "cannot move to queued" in msg
    assert "allowed from running: running" not in msg
    assert "stopping" in msg and "completed" in msg and "failed" in msg
    assert info.value.current is JobState.running and info.value.requested is JobState.queued
    assert set(info.value.allowed) == ALLOWED_TRANSITIONS[JobState.running]
    with pytest.raises(InvalidTransition, match="cannot move to running"):
        store.transition("j", "running")  # no self-transitions
    with pytest.raises(StoreError, match="unknown job state 'paused'"):
        store.transition("j", "paused")
    assert store.get("j").state is JobState.running  # refused moves change nothing

    failed = store.transition("j", JobState.failed, "learner exited with code 3")
    assert failed.state is JobState.failed and failed.error == "learner exited with code 3"
    assert failed.updated_at >= failed.created_at
    with pytest.raises(InvalidTransition, match=r"allowed from failed: queued\)"):
        store.transition("j", "running")

    resumed = store.transition("j", JobState.queued, "resume from checkpoint")
    assert resumed.state is JobState.queued and resumed.error is None

    history = store.transitions("j")
    assert [(h["from_state"], h["to_state"]) for h in history] == [
        (None, "queued"),
        ("queued", "starting"),
        ("starting", "running"),
        ("running", "failed"),
        ("failed", "queued"),
    ]
    assert [h["reason"] for h in history][1:] == [
        "scheduled",
        "",
        "learner exited with code 3",
        "resume from checkpoint",
    ]
    times = [h["at"] for h in history]
    assert times == sorted(times)
    assert set(history[0]) == {"at", "from_state", "to_state", "reason"}


def test_every_table_entry_is_accepted_and_nothing_else() -> None:
    with JobStore(":memory:") as s:
        for src in JobState:
            for dst in JobState:
                job = f"{src.value}-{dst.value}"
                s.create(job, {}, actors=1, state=src)
                if dst in ALLOWED_TRANSITIONS[src]:
                    assert s.transition(job, dst).state is dst
                else:
                    with pytest.raises(InvalidTransition):
                        s.transition(job, dst)


def test_update_merges_progress(store: JobStore) -> None:
    store.create("u", CONFIG, actors=2)
    before = store.get("u")
    rec = store.update("u", progress={"env_steps": 100, "updates": 1})
    rec = store.update("u", progress={"env_steps": 200, "return": -3.5}, actors=6, last_checkpoint="ckpt/200.pt")
    assert rec.progress == {"env_steps": 200, "updates": 1, "return": -3.5}
    assert rec.actors == 6 and rec.last_checkpoint == "ckpt/200.pt"
    assert rec.config == CONFIG and rec.out_dir is None and rec.state is JobState.queued  # untouched
    assert rec.updated_at >= before.updated_at

    rec = store.update("u", out_dir="runs/u", error="warning: slow actor", config={"algo": "ma_bon"})
    assert rec.out_dir == "runs/u" and rec.error == "warning: slow actor" and rec.config == {"algo": "ma_bon"}
    assert rec.progress["updates"] == 1 and rec.actors == 6
    assert store.update("u") == rec  # nothing given, nothing changed
    with pytest.raises(StoreError, match="actors must be"):
        store.update("u", actors=True)  # a bool is an int to the checker, not to the store
    with pytest.raises(StoreError, match="progress must be a dict"):
        store.update("u", progress=[1])  # type: ignore[arg-type]  # progress that is no dict, on purpose
    assert store.get("u") == rec


# -- metrics -----------------------------------------------------------------------------------------------------------


def test_append_and_poll_without_duplicates_or_gaps(store: JobStore) -> None:
    store.create("m", CONFIG, actors=1)
    assert store.metrics("m") == [] and store.last_step("m") is None
    steps = list(range(0, 2500, 100))
    assert store.append_metrics("m", rows(steps[:10])) == 10

    got: list[dict] = []
    cursor: int | None = None
    polls = 0
    while True:
        if polls == 2:
            store.append_metrics("m", rows(steps[10:]))  # more rows arrive while a client is polling
        page = store.metrics("m", since=cursor, limit=4)
        polls += 1
        if not page:
            break
        assert len(page) <= 4
        got.extend(page)
        cursor = page[-1]["env_steps"]
    assert [r["env_steps"] for r in got] == steps  # every step once, in order
    assert got == store.metrics("m")
    assert store.last_step("m") == steps[-1]
    assert [r["env_steps"] for r in store.metrics("m", since=150)] == steps[2:]
    assert [r["env_steps"] for r in store.metrics("m", since=-1, limit=2)] == [0, 100]
    assert store.metrics("m", since=steps[-1]) == []
    assert store.metrics("m", limit=0) == []


def test_names_filter(store: JobStore) -> None:
    store.create("n", CONFIG, actors=1)
    store.append_metrics("n", [{"env_steps": 1, "return": 1.5, "loss": 0.3}, {"env_steps": 2, "loss": 0.2, "fps": 9}])
    assert store.metrics("n", names=["return"]) == [{"env_steps": 1, "return": 1.5}, {"env_steps": 2}]
    assert store.metrics("n", names=["loss", "fps", "nope"], since=1) == [{"env_steps": 2, "loss": 0.2, "fps": 9}]
    assert store.metrics("n", names=[]) == [{"env_steps": 1}, {"env_steps": 2}]


def test_reemitted_step_replaces_and_resume_cuts(store: JobStore) -> None:
    store.create("r", CONFIG, actors=1)
    store.append_metrics("r", rows(range(0, 1000, 100)))
    assert store.append_metrics("r", [{"env_steps": 300, "return": 99.0}]) == 1
    assert store.metrics("r", since=200, limit=1) == [{"env_steps": 300, "return": 99.0}]
    assert len(store.metrics("r")) == 10
    # a repeated step inside one batch is written once; the last copy wins
    assert store.append_metrics("r", [{"env_steps": 400, "v": 1}, {"env_steps": 400, "v": 2}]) == 1
    assert store.metrics("r", since=300, limit=1) == [{"env_steps": 400, "v": 2}]

    # the job failed at step 900; it resumes from the checkpoint taken at step 500
    assert store.cut_metrics("r", 500) == 4
    assert store.last_step("r") == 500
    assert store.cut_metrics("r", 500) == 0
    store.append_metrics("r", rows(range(600, 1200, 100), resumed=True))
    all_rows = store.metrics("r")
    assert [r["env_steps"] for r in all_rows] == list(range(0, 1200, 100))
    assert all(r.get("resumed") for r in all_rows if r["env_steps"] > 500)
    assert not any(r.get("resumed") for r in all_rows if r["env_steps"] <= 500)


def test_non_finite_floats_round_trip(store: JobStore) -> None:
    store.create("nan", CONFIG, actors=1)
    store.append_metrics(
        "nan", [{"env_steps": 7, "loss": float("nan"), "hi": float("inf"), "lo": float("-inf"), "v": [1.0, math.nan]}]
    )
    (row,) = store.metrics("nan")
    assert math.isnan(row["loss"]) and row["hi"] == math.inf and row["lo"] == -math.inf
    assert row["v"][0] == 1.0 and math.isnan(row["v"][1])
    rec = store.update("nan", progress={"return": float("nan")})
    assert math.isnan(rec.progress["return"]) and math.isnan(store.get("nan").progress["return"])


def test_bad_metric_rows(store: JobStore) -> None:
    store.create("b", CONFIG, actors=1)
    store.append_metrics("b", rows([1]))
    for bad, pattern in [
        ({"return": 1.0}, "has no 'env_steps'"),
        ({"env_steps": 1.5}, "'env_steps' must be an int"),
        ({"env_steps": "10"}, "'env_steps' must be an int"),
        ({"env_steps": True}, "'env_steps' must be an int"),
        ({"env_steps": 3, "x": object()}, "cannot be stored as JSON"),
        ([("env_steps", 3)], "must be a dict"),
    ]:
        with pytest.raises(StoreError, match=pattern):
            store.append_metrics("b", [*rows([2]), bad])  # type: ignore[list-item]  # bad rows, on purpose
    assert [r["env_steps"] for r in store.metrics("b")] == [1]  # a bad batch writes nothing
    assert store.append_metrics("b", []) == 0
    with pytest.raises(StoreError, match="since must be an int"):
        store.metrics("b", since="5")  # type: ignore[arg-type]  # a str for an int, on purpose
    with pytest.raises(StoreError, match="limit must be"):
        store.metrics("b", limit=-1)


# -- persistence -------------------------------------------------------------------------------------------------------


def test_close_and_reopen_keeps_everything(tmp_path: Path) -> None:
    path = tmp_path / "jobs.sqlite"
    with JobStore(path) as s:
        assert s.journal_mode == "wal"
        s.create("p", CONFIG, actors=3, out_dir="runs/p")
        s.transition("p", "starting")
        s.transition("p", "running")
        s.update("p", progress={"env_steps": 500}, last_checkpoint="ckpt/500.pt")
        s.append_metrics("p", [*rows(range(0, 600, 100)), {"env_steps": 600, "loss": math.nan}])
        s.create("q", {}, actors=1)
        before = (s.list(), s.transitions("p"), s.metrics("p"))
    with pytest.raises(StoreError, match="closed"):
        s.get("p")
    s.close()  # closing twice is fine

    with JobStore(str(path)) as s:
        jobs, history, metrics = s.list(), s.transitions("p"), s.metrics("p")
        assert jobs == before[0] and history == before[1]
        assert metrics[:-1] == before[2][:-1] and math.isnan(metrics[-1]["loss"])
        assert s.get("p").state is JobState.running and s.get("p").last_checkpoint == "ckpt/500.pt"
        assert s.last_step("p") == 600
        s.transition("p", "stopping")  # and it keeps working

    conn = sqlite3.connect(path)
    try:
        assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        assert conn.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION
    finally:
        conn.close()


def test_newer_schema_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "future.sqlite"
    conn = sqlite3.connect(path)
    conn.execute(f"PRAGMA user_version = {SCHEMA_VERSION + 1}")
    conn.commit()
    conn.close()
    with pytest.raises(StoreError, match=rf"schema version {SCHEMA_VERSION + 1}.*newer Convoy.*Upgrade Convoy"):
        JobStore(path)


def test_not_a_database_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "junk.sqlite"
    path.write_bytes(b"this is not sqlite at all" * 100)
    with pytest.raises(StoreError, match="not a usable Convoy job store"):
        JobStore(path)


def test_memory_store() -> None:
    with JobStore(":memory:") as s:
        s.create("mem", {}, actors=1)
        assert s.exists("mem")


# -- concurrency -------------------------------------------------------------------------------------------------------


def test_concurrent_writers_and_poller(tmp_path: Path) -> None:
    jobs, batches, per_batch = [f"w{i}" for i in range(4)], 40, 5
    errors: list[BaseException] = []
    seen: dict[str, list[int]] = {j: [] for j in jobs}
    done = threading.Event()

    with JobStore(tmp_path / "jobs.sqlite") as s:
        for j in jobs:
            s.create(j, CONFIG, actors=1)

        def writer(job: str) -> None:
            try:
                for b in range(batches):
                    s.append_metrics(job, rows(range(b * per_batch, (b + 1) * per_batch)))
                    s.update(job, progress={"env_steps": (b + 1) * per_batch - 1})
            except BaseException as exc:
                errors.append(exc)

        def poller() -> None:
            cursors: dict[str, int | None] = dict.fromkeys(jobs)
            try:
                while True:
                    finished = done.is_set()  # read before polling so the last pass sees everything
                    for j in jobs:
                        page = s.metrics(j, since=cursors[j], limit=7, names=["return"])
                        if page:
                            seen[j].extend(r["env_steps"] for r in page)
                            cursors[j] = page[-1]["env_steps"]
                    s.count_by_state()
                    if finished and (errors or all(cursors[j] == batches * per_batch - 1 for j in jobs)):
                        return
            except BaseException as exc:
                errors.append(exc)

        threads = [threading.Thread(target=writer, args=(j,)) for j in jobs]
        poll = threading.Thread(target=poller)
        poll.start()
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout=30)
        done.set()
        poll.join(timeout=30)
        assert not poll.is_alive()
        assert errors == []
        expected = list(range(batches * per_batch))
        for j in jobs:
            assert [r["env_steps"] for r in s.metrics(j)] == expected
            assert seen[j] == expected  # the poller got every row exactly once, in order
            assert s.get(j).progress["env_steps"] == expected[-1]


# -- queue, counts, delete ---------------------------------------------------------------------------------------------


def test_queue_position_and_count_by_state(store: JobStore) -> None:
    assert store.count_by_state() == {s.value: 0 for s in JobState}
    for j in ("q1", "q2", "q3"):
        store.create(j, {}, actors=1)
    assert [store.queue_position(j) for j in ("q1", "q2", "q3")] == [1, 2, 3]
    store.transition("q1", "starting")
    assert store.queue_position("q1") is None
    assert [store.queue_position(j) for j in ("q2", "q3")] == [1, 2]
    store.transition("q2", "stopped", "cancelled")
    assert store.queue_position("q3") == 1

    counts = store.count_by_state()
    assert set(counts) == {s.value for s in JobState}
    assert counts == {
        "queued": 1,
        "starting": 1,
        "running": 0,
        "stopping": 0,
        "stopped": 1,
        "completed": 0,
        "failed": 0,
    }


def test_delete_removes_everything(store: JobStore, tmp_path: Path) -> None:
    store.create("d", CONFIG, actors=1)
    store.create("keep", CONFIG, actors=1)
    store.transition("d", "starting")
    store.append_metrics("d", rows(range(5)))
    store.append_metrics("keep", rows(range(3)))
    store.delete("d")
    assert not store.exists("d")
    with pytest.raises(UnknownJob):
        store.get("d")
    with pytest.raises(UnknownJob):
        store.delete("d")
    assert [j.id for j in store.list()] == ["keep"] and len(store.metrics("keep")) == 3

    conn = sqlite3.connect(tmp_path / "db" / "jobs.sqlite")
    try:
        for table in ("jobs", "transitions", "metrics"):
            column = "id" if table == "jobs" else "job_id"
            assert conn.execute(f"SELECT COUNT(*) FROM {table} WHERE {column} = 'd'").fetchone()[0] == 0
    finally:
        conn.close()

    store.create("d", {}, actors=1)  # the id is free again, with a fresh history
    assert store.metrics("d") == [] and len(store.transitions("d")) == 1
