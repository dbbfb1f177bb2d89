"""Run one distributed job on this machine: a learner and N actors as processes, connected by Zenoh on loopback,
watched until the learner has finished — what ``convoy train`` does by default.

The runner opens the job's root Zenoh session (a router on a free loopback port; its children are clients of it
that listen on nothing, so every link is opened once, by one side: docs/architecture.md), starts the processes
through a :class:`~services.procs.ProcessGroup`, follows their liveliness tokens and metrics, shows progress
(steps, return, updates/s, policy lag, actors alive), reacts to crashes (respawn / restart / fail with the reason)
and takes live scaling requests (``scale``).
"""

from __future__ import annotations

import collections
import json
import logging
import math
import tempfile
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from convoy.config import MAX_DEMO_ROUNDS, JobConfig
from convoy.learner.runlog import ProgressDisplay
from convoy.protocol import keys, wire
from convoy.protocol.inbox import Inbox
from convoy.protocol.session import ZenohSettings, open_session
from convoy.services.procs import Event, JobFailed, JobRefused, ProcessGroup

log = logging.getLogger(__name__)


class MetricReports:
    """What a supervisor (``JobRunner``, the job service) hears on a job's ``metrics/**`` keys: each live actor's last
    report, the learner's last row, and how many messages it could not use. Any well-formed message is survivable:
    one lacking what it is used for, or from an actor id that is not alive, is counted in ``bad`` and ignored."""

    def __init__(self) -> None:
        self.actors: dict[str, dict[str, float]] = {}  # bounded: only the job's live actors get an entry
        self.learner: dict[str, float] = {}
        self.bad = 0

    def take(self, msg: wire.Message, live: set[str]) -> str:
        """Sort one message: ``actor``, ``resumed`` (a learner back from its checkpoint), ``demonstration`` (a
        learner's DAgger round, 1 ≤ round ≤ rounds ≤ 64), ``row`` (a learner row with a usable step count),
        ``other`` (a learner message with no row, e.g. its last) or ``bad``."""
        values, role, ident = msg.body["values"], msg.body["role"], msg.body["id"]
        kind = "bad"
        if role == "actor" and (ident in live or ident in self.actors):
            self.actors[ident], kind = values, "actor"
        elif role != "learner":
            pass
        elif "resumed_updates" in values or "resumed_env_steps" in values:
            kind = "resumed" if "resumed_updates" in values and "resumed_env_steps" in values else "bad"
        elif "demo_round" in values or "demo_rounds" in values:
            k, n = values.get("demo_round", math.nan), values.get("demo_rounds", math.nan)
            kind = "demonstration" if 1 <= k <= n <= MAX_DEMO_ROUNDS and k == int(k) and n == int(n) else "bad"
        elif "return" not in values:
            kind = "other"
        elif math.isfinite(values.get("env_steps", math.nan)) and values["env_steps"] >= 0:
            self.learner, kind = values, "row"
        self.bad += kind == "bad"
        return kind

    def dropped(self, own_role: str, own: Mapping[str, int]) -> dict[str, dict[str, int]]:
        """Every message the job dropped, by role and reason: the learner's and the actors' from their last metrics
        (``dropped_<reason>`` values: counts since each process started), the supervisor's own inbox (``own``) and
        the metrics messages it could not use."""
        summed: collections.Counter[str] = collections.Counter()
        for values in self.actors.values():
            summed.update(wire.dropped_reasons(values))
        return {
            "learner": wire.dropped_reasons(self.learner),
            "actors": {"garbage": summed["garbage"], "overflow": summed["overflow"]},
            own_role: {**dict(own), "unusable-metrics": self.bad},
        }


class AliveSet:
    """Who holds a liveliness token of a job right now (a liveliness subscriber with history)."""

    def __init__(self, session: Any, job_id: str) -> None:
        import zenoh

        self._lock = threading.Lock()
        self.members: set[tuple[str, str]] = set()
        self._put, self._delete = zenoh.SampleKind.PUT, zenoh.SampleKind.DELETE
        self._sub = session.liveliness().declare_subscriber(keys.alive_all(job_id), self._on, history=True)

    def _on(self, sample: Any) -> None:
        parsed = keys.parse_alive(str(sample.key_expr))
        if parsed is None:
            return
        member = (parsed[1], parsed[2])
        with self._lock:
            if sample.kind == self._delete:
                self.members.discard(member)
            else:
                self.members.add(member)

    def count(self, role: str) -> int:
        with self._lock:
            return sum(1 for r, _ in self.members if r == role)

    def close(self) -> None:
        self._sub.undeclare()

    def ids(self, role: str) -> set[str]:
        with self._lock:
            return {i for r, i in self.members if r == role}


class JobRunner:
    def __init__(
        self,
        job_id: str,
        job: JobConfig,
        out_dir: str | Path,
        progress: bool = True,
        on_event: Any = None,
    ) -> None:
        self.job_id, self.job, self.out_dir = keys.check_id(job_id, "job id"), job, Path(out_dir)
        self.progress = progress
        self.on_event = on_event or (lambda ev: print(f"[{ev.kind}] {ev.ident} {ev.detail}".rstrip(), flush=True))
        self._wanted: int | None = None
        self._lock = threading.Lock()
        self.group: ProcessGroup | None = None
        self.alive: AliveSet | None = None
        self.last_row: dict[str, float] = {}
        self.reports = MetricReports()
        self.events: list[Event] = []
        self.resumes: list[dict[str, float]] = []
        self.started = threading.Event()
        self._stop = threading.Event()

    def stop(self) -> None:
        """Ask ``run`` to stop the job: processes get SIGTERM (the learner checkpoints), then ``run`` returns."""
        self._stop.set()

    def scale(self, actors: int) -> None:
        """Ask for ``actors`` actor processes; takes effect within the runner's next poll (live)."""
        if actors < 1:
            raise ValueError(f"actors: must be ≥ 1 (got {actors})")
        with self._lock:
            self._wanted = actors

    def run(self) -> dict[str, Any]:
        """Run the job to its end; the learner's summary (a population's as ``{"runs": [one per seed]}``), or {}
        when it stopped early."""
        self.out_dir.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(prefix="convoy-zenoh-") as private:  # 0700: the job's credential
            return self._run(self.job.runtime.zenoh.secured(private, self.job_id).rooted())

    def _run(self, root: ZenohSettings) -> dict[str, Any]:
        session = open_session(root)
        display = ProgressDisplay(self.job.steps, self.progress)
        group = self.group = ProcessGroup(self.job_id, self.job, str(self.out_dir), root.child())
        try:
            self.alive = AliveSet(session, self.job_id)
            metrics = Inbox({"metrics"}, maxlen=4096)
            self._declared = session.declare_subscriber(keys.metrics_all(self.job_id), metrics)  # kept referenced
            stop_pub = session.declare_publisher(keys.ctl(self.job_id, "stop"))
            group.start_learner()
            group.scale_actors(self.job.runtime.actors)
            self.started.set()
            while "learner" not in group.finished and not self._stop.is_set():
                with self._lock:
                    wanted, self._wanted = self._wanted, None
                if wanted is not None:
                    group.scale_actors(wanted)
                for msg in metrics.drain():  # first: the learner's last row tells poll whether actors may leave
                    self._metric(msg, display)
                for ev in group.poll(learner_has_data=self.last_row.get("env_steps", 0) >= self.job.steps):
                    self.events.append(ev)
                    self.on_event(ev)
                    if ev.kind == "failed":
                        raise (JobRefused if ev.refused else JobFailed)(ev.detail)
                time.sleep(0.05)
            stop_pub.put(wire.encode("command", {"op": "stop", "args": {}}, "runner"))
            finished = "learner" in group.finished
        finally:
            group.stop_all()
            display.close()
            session.close()
        paths = [d / "summary.json" for d in self.job.member_dirs(self.out_dir)]
        # a job stopped early has no summary of its own (one left by an earlier run in out_dir is not this job's)
        if not (finished and all(p.is_file() for p in paths)):
            return {}
        summaries = []
        for path in paths:
            summary = json.loads(path.read_text())
            summary["dropped_elsewhere"] = self.drop_report(metrics)
            tmp = path.with_suffix(".json.tmp")
            tmp.write_text(json.dumps(summary, indent=2) + "\n")  # as the learner wrote it
            tmp.replace(path)
            summaries.append(summary)
        return {"runs": summaries} if self.job.runs else summaries[0]

    def drop_report(self, metrics: Inbox) -> dict[str, Any]:
        """What the learner's ``dropped_by_reason`` does not see: the actors' drops and the supervisor's own."""
        report = self.reports.dropped("supervisor", metrics.dropped)
        report.pop("learner")
        return report

    def _metric(self, msg: wire.Message, display: ProgressDisplay) -> None:
        """Take in one metrics message (``MetricReports.take``): a learner resume is said, a learner row shown."""
        live = self.alive.ids("actor") if self.alive else set()
        kind, values = self.reports.take(msg, live), msg.body["values"]
        if kind == "resumed":
            self.resumes.append(values)
            log.info(
                f"[resumed] learner from its checkpoint: {values['resumed_env_steps']:,.0f} env steps, "
                f"{values['resumed_updates']:,.0f} updates, {values.get('resumed_replay_rows', 0):,.0f} replay rows"
            )
        if kind != "row":
            return
        row = dict(values)
        row["actors_alive"] = float(self.alive.count("actor")) if self.alive else math.nan
        row["actor_env_steps_per_s"] = sum(
            m.get("env_steps_per_s", 0.0) for i, m in self.reports.actors.items() if i in live
        )
        self.last_row = row
        display.update(int(row["env_steps"]), row)
