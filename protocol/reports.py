"""Process reports: what a job's processes tell their supervisors, as JSON lines in the job's ``reports.jsonl``.

The job service learns from these records that a process crashed, was respawned or backed off, that a role failed
for good, and why a process gave up (its error: an exception, or a reason such as the learner's "no chunk from
any actor") — never by reading the human log. A process writes them through ``logging``: its ERROR records (and
the records a supervisor logs with an ``event``) go to the reports file as well as to its log.
"""

from __future__ import annotations

import json
import logging
import math
import os
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TextIO

REPORTS_FILE = "reports.jsonl"
EVENTS = ("exited", "crashed", "backoff", "respawned", "failed")  # a supervisor's events about its processes
KINDS = (*EVENTS, "error")  # "error": a process's own last word (an exception, or why it gave up)
MAX_DETAIL = 2000  # characters kept of one record's detail


@dataclass(frozen=True)
class Report:
    kind: str  # one of KINDS
    source: str  # who it is about: "learner-0", "h-job.actor-3.1", a host's name
    detail: str = ""  # "exit code -9", "actor crashed 4 times within 60 s (…)", "OutOfMemoryError: …"
    time: float = 0.0  # seconds since the epoch

    @classmethod
    def parse(cls, line: str) -> Report | None:
        """A record from one line, or None for a line that is not one (torn, foreign or hostile: values are
        checked, not only keys)."""
        try:
            raw = json.loads(line)
        except ValueError:
            return None
        if not isinstance(raw, dict) or raw.get("kind") not in KINDS:
            return None
        source, detail, when = raw.get("source"), raw.get("detail", ""), raw.get("time", 0.0)
        if not isinstance(source, str) or not isinstance(detail, str) or not isinstance(when, int | float):
            return None
        return cls(raw["kind"], source[:200], detail[:MAX_DETAIL], float(when) if math.isfinite(when) else 0.0)


def append(path: str | Path, report: Report) -> None:
    """One record, in one ``write`` on a file opened for appending, so records of concurrent processes never
    interleave within a line."""
    line = json.dumps({**asdict(report), "detail": report.detail[:MAX_DETAIL], "time": report.time or time.time()})
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        os.write(fd, (line + "\n").encode())
    finally:
        os.close(fd)


def read(path: str | Path, last: int | None = None) -> list[Report]:
    """The records of a reports file (the ``last`` ones), skipping lines that are not records."""
    try:
        found = _records(Path(path).read_text(errors="replace"))
    except OSError:
        return []
    return found[-last:] if last else found


def _records(text: str) -> list[Report]:
    return [r for r in map(Report.parse, text.splitlines()) if r is not None]


class ReportTail:
    """The records appended to a reports file since the last ``new()`` (from its end when made: only what happens
    from now); whole lines only, the rest next time."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.offset = self.path.stat().st_size if self.path.is_file() else 0

    def new(self) -> list[Report]:
        try:
            with self.path.open("rb") as fh:
                fh.seek(self.offset)
                data = fh.read()
        except OSError:
            return []
        end = data.rfind(b"\n") + 1
        self.offset += end
        return _records(data[:end].decode(errors="replace"))


class ReportHandler(logging.Handler):
    """Writes a process's ERROR records as ``error`` reports (the exception's type and message when there is one)
    and records logged with ``extra={"event": kind, "source": …, "detail": …}`` as that event."""

    def __init__(self, path: str | Path, source: str) -> None:
        super().__init__(logging.INFO)
        self.path, self.source = Path(path), source

    def emit(self, record: logging.LogRecord) -> None:
        event = getattr(record, "event", None)
        if event in EVENTS:
            report = Report(event, getattr(record, "source", self.source), getattr(record, "detail", ""))
        elif record.levelno >= logging.ERROR:
            exc = record.exc_info[1] if record.exc_info else None
            detail = f"{type(exc).__qualname__}: {exc}" if exc is not None else record.getMessage()
            report = Report("error", self.source, detail)
        else:
            return
        try:
            append(self.path, report)
        except OSError:
            self.handleError(record)


class _Stdout(logging.StreamHandler[TextIO]):
    """A stream handler on whatever ``sys.stdout`` is when it writes (a process's log is its stdout; tests swap it)."""

    def __init__(self) -> None:
        super().__init__(sys.stdout)

    @property
    def stream(self) -> TextIO:
        return sys.stdout

    @stream.setter
    def stream(self, _value: object) -> None:
        pass


def setup_logging(reports: str | Path | None = None, source: str = "", timestamps: bool = False) -> None:
    """A Convoy process's logging: INFO and above to stdout as plain lines (its log), each prefixed ``[source]``
    when given (a host's log interleaves its processes) and with the time when asked; and, with ``reports``, its
    ERROR records and supervisor events to that reports file. A second call replaces the first's handlers."""
    root = logging.getLogger("convoy")
    for handler in list(root.handlers):
        root.removeHandler(handler)
    prefix = f"[{source.replace('%', '%%')}] " if source else ""
    fmt = ("%(asctime)s " if timestamps else "") + prefix + "%(message)s"
    out = _Stdout()
    out.setFormatter(logging.Formatter(fmt, "%H:%M:%S"))
    root.addHandler(out)
    if reports is not None:
        root.addHandler(ReportHandler(reports, source))
    root.setLevel(logging.INFO)
