"""A host agent: runs one job's roles on this machine and keeps them running — ``convoy host``.

On one laptop ``convoy train`` does this itself (``services.jobrunner``). Across machines each host runs a host
agent for the roles it offers (a learner host, actor hosts), all joined through Zenoh routers: the agent starts its
processes with a :class:`~services.procs.ProcessGroup` (respawn, restart from checkpoint, fail after repeated
crashes), declares its own liveliness token, and takes ``scale`` and ``stop`` commands on
``convoy/hosts/<name>/cmd`` (wire kind ``command``: ``{"op": "scale", "args": {"actors": n}}``). It exits when its
learner has finished the job, or — on an actor host — when the learner's budget says the job has all its data.
"""

from __future__ import annotations

import logging
import signal
import tempfile
import time
from pathlib import Path
from typing import Any

from convoy.config import JobConfig
from convoy.protocol import keys
from convoy.protocol.inbox import Inbox
from convoy.protocol.reports import REPORTS_FILE, setup_logging
from convoy.protocol.session import ZenohSettings, open_session
from convoy.services.procs import JobFailed, ProcessGroup

log = logging.getLogger(__name__)


class HostAgent:
    def __init__(
        self,
        name: str,
        job_id: str,
        job: JobConfig,
        roles: tuple[str, ...],
        actors: int,
        out_dir: str | Path,
        settings: ZenohSettings,
    ) -> None:
        self.name, self.job_id, self.job, self.roles = keys.check_id(name, "host name"), job_id, job, roles
        self.actors, self.out_dir, self.settings = actors, Path(out_dir), settings
        self.stopping = False

    def stop(self, *_: Any) -> None:
        self.stopping = True

    def run(self) -> int:
        with tempfile.TemporaryDirectory(prefix="convoy-zenoh-") as private:  # 0700: the job's credential
            return self._run(self.settings.secured(private, self.job_id).rooted())

    def _run(self, settings: ZenohSettings) -> int:
        """Run the roles with ``settings`` (on one machine the agent's session is its children's router)."""
        session = open_session(settings)
        cmds, budget = Inbox({"command"}, 64), Inbox({"budget"}, 4)
        keep = [  # the token last: whoever sees it (the job service) may send commands, and they are heard
            session.declare_subscriber(keys.host(self.name, "cmd"), cmds),
            session.declare_subscriber(keys.ctl(self.job_id, "budget"), budget),
            session.liveliness().declare_token(keys.alive(self.job_id, "host", self.name)),
        ]
        child = settings.child()
        group = ProcessGroup(self.job_id, self.job, str(self.out_dir), child, roles=self.roles, host=self.name)
        ingested = 0
        try:
            if "learner" in self.roles:
                group.start_learner()
            if "actor" in self.roles:
                group.scale_actors(self.actors)
            while not self.stopping:
                for msg in cmds.drain():
                    op, args = msg.body["op"], msg.body["args"]
                    if op == "scale" and "actor" in self.roles and isinstance(args.get("actors"), int):
                        if not self._has_data(group, ingested):  # at the job's end, no actor is started again
                            group.scale_actors(max(0, args["actors"]))
                    elif op == "stop":
                        self.stopping = True
                last = budget.latest()
                if last is not None:
                    ingested = last.body["ingested_steps"]
                for ev in group.poll(learner_has_data=ingested >= self.job.steps):
                    extra = {"event": ev.kind, "source": ev.ident, "detail": ev.detail}  # also a report
                    log.info(f"{ev.kind} {ev.ident} {ev.detail}".rstrip(), extra=extra)
                    if ev.kind == "failed":
                        raise JobFailed(ev.detail)
                if self._done(group, ingested):
                    break
                time.sleep(0.05)
        finally:
            group.stop_all()
            del keep
            session.close()
        return 0

    def _has_data(self, group: ProcessGroup, ingested: int) -> bool:
        """Whether the job has all its steps (the learner's budget, or this host's learner said so)."""
        return ingested >= self.job.steps or (group.has_data is not None and group.has_data.is_set())

    def _done(self, group: ProcessGroup, ingested: int) -> bool:
        """A learner host is done when its learner finished; an actor host when the job has all its data."""
        if "learner" in self.roles:
            return "learner" in group.finished
        return ingested >= self.job.steps or ("actor" in group.finished and not group.actors)


def run_host(
    name: str,
    job_id: str,
    job: JobConfig,
    roles: tuple[str, ...],
    actors: int,
    out_dir: str,
    settings: ZenohSettings,
) -> int:
    agent = HostAgent(name, job_id, job, roles, actors, out_dir, settings)
    setup_logging(Path(out_dir) / REPORTS_FILE, name)  # its processes' events, for the job service
    signal.signal(signal.SIGTERM, agent.stop)
    signal.signal(signal.SIGINT, agent.stop)
    return agent.run()


def run_router(settings: ZenohSettings) -> int:
    """A Zenoh router in this process (``convoy router``) until SIGTERM/SIGINT: what ``zenohd`` does, for machines
    where the ``eclipse/zenoh`` image or binary is not at hand."""
    stopping = []
    signal.signal(signal.SIGTERM, lambda *_: stopping.append(1))
    signal.signal(signal.SIGINT, lambda *_: stopping.append(1))
    session = open_session(settings.model_copy(update={"mode": "router"}))
    log.info("router listening on %s", ", ".join(settings.listen) or "tcp/[::]:7447")
    try:
        while not stopping:
            time.sleep(0.1)
    finally:
        session.close()
    return 0
