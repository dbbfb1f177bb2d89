"""Process reports: the records a job's processes write for the job service, and what it makes of them."""

from __future__ import annotations

import json
import logging
import multiprocessing as mp
from pathlib import Path

import pytest

from convoy.protocol.reports import REPORTS_FILE, Report, ReportTail, append, read, setup_logging


@pytest.fixture(autouse=True)
def _restore_logging():
    """setup_logging replaces the ``convoy`` logger's handlers: give them back afterwards."""
    logger = logging.getLogger("convoy")
    handlers, level = list(logger.handlers), logger.level
    yield
    logger.handlers[:] = handlers
    logger.setLevel(level)


def test_records_round_trip_and_hostile_lines_are_skipped(tmp_path: Path) -> None:
    path = tmp_path / "sub" / REPORTS_FILE  # its folder is made on the first record
    tail = ReportTail(path)
    append(path, Report("crashed", "actor-3", "exit code -9"))
    with path.open("a") as fh:
        for line in ("not json", "[]", '{"kind": "rm -rf", "source": "x"}', '{"kind": "error", "source": 7}',
                     '{"kind": "error", "source": "x", "detail": "y", "time": "now"}',
                     json.dumps({"kind": "error", "source": "s" * 10_000, "detail": "d" * 10_000})):  # fmt: skip
            fh.write(line + "\n")
        fh.write('{"kind": "failed", "source": "learner-0", "det')  # torn: not yet a whole line
    got = tail.new()
    assert [(r.kind, r.source, r.detail) for r in got[:1]] == [("crashed", "actor-3", "exit code -9")]
    assert len(got) == 2 and len(got[1].source) == 200 and len(got[1].detail) == 2000  # values bounded
    assert got[0].time > 0
    assert tail.new() == []  # the torn line waits for its end
    with path.open("a") as fh:
        fh.write('ail": "gave up"}\n')
    assert [(r.kind, r.detail) for r in tail.new()] == [("failed", "gave up")]
    assert len(read(path)) == 3 and read(path, last=1)[0].kind == "failed"
    assert read(tmp_path / "missing.jsonl") == []


def test_errors_and_events_logged_by_a_process_become_reports(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    path = tmp_path / REPORTS_FILE
    setup_logging(path, "learner-0")
    log = logging.getLogger("convoy.learner.service")
    log.info("an ordinary line")  # the log only
    log.warning("replay unusable")  # the log only
    log.error("no chunk from any actor for 1 s")
    try:
        raise MemoryError("CUDA out of memory")
    except MemoryError:
        log.exception("learner-0 died")
    log.info("crashed actor-3 exit code -9", extra={"event": "crashed", "source": "actor-3", "detail": "exit code -9"})
    out = capsys.readouterr().out
    assert "[learner-0] an ordinary line" in out and "[learner-0] no chunk from any actor" in out
    assert "Traceback" in out  # the log keeps the traceback; the report keeps its last word
    assert [(r.kind, r.source, r.detail) for r in read(path)] == [
        ("error", "learner-0", "no chunk from any actor for 1 s"),
        ("error", "learner-0", "MemoryError: CUDA out of memory"),
        ("crashed", "actor-3", "exit code -9"),
    ]


def _dies(reports: str) -> None:
    from convoy.services.procs import _role_main

    def run() -> int:
        raise RuntimeError("the env exploded")

    _role_main("actor-0", reports, run)


def test_a_role_process_that_raises_reports_its_exception_and_exits_1(tmp_path: Path) -> None:
    path = tmp_path / REPORTS_FILE
    proc = mp.get_context("spawn").Process(target=_dies, args=(str(path),))
    proc.start()
    proc.join(60)
    assert proc.exitcode == 1
    assert [(r.kind, r.source, r.detail) for r in read(path)] == [
        ("error", "actor-0", "RuntimeError: the env exploded")
    ]
