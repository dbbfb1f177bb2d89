"""Local process management for one job: start, respawn, scale and stop actor and learner processes.

Used by the job runner of ``convoy train`` and by host agents (``convoy host``) alike. Processes start from a
*forkserver* that has imported what every role needs (torch, the envs, the algorithms) once and never opens a Zenoh
session: a role process is a fork of it, so the job's processes do not each spend ~1.5 s of CPU importing torch side
by side at start-up, and a crashed actor is back in a fraction of a second. Forking the job's own process is not an
option (fork after a Zenoh session is open loses every message); where the platform has no forkserver the ``spawn``
method is used. Processes get plain-data arguments (job config, Zenoh settings) and are tracked by PID. A crashed
actor is respawned under a new id (its seed advanced, so it does not replay the same episodes); a crashed learner is
restarted and resumes from its checkpoint, except one that diverged (``DIVERGED``: a restart would diverge again),
which fails the job at once, and a process that refused the job's configuration (a ``ConfigError``: a teacher
checkpoint that is gone or refused, a tracker that cannot start; exit code ``CONFIG``), which fails it at once with
that refusal as the reason: a respawn would only refuse again. Each role has its own budget within
``restart_window_s``: a few learner crashes (``max_restarts``: each costs a resume) and many actor deaths
(``actor_max_restarts``: actors come and go), past which the job fails with the reason. An actor that keeps dying
at start (a crash loop, not churn) is respawned after a doubling delay (``restart_backoff_s``). Exit code 0 means a
process finished its part of the job and is not restarted, unless an actor leaves while its local learner still lacks
the job's steps (then it is respawned: ``poll``).
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import signal
import time
import zlib
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from convoy.config import ConfigError, JobConfig
from convoy.protocol.exitcodes import CONFIG, DIVERGED
from convoy.protocol.reports import REPORTS_FILE, setup_logging
from convoy.protocol.reports import read as read_reports
from convoy.protocol.session import ZenohSettings

# What the forkserver imports before it forks any role process (no Zenoh session, no torch op, no CUDA there).
# torch._dynamo: torch imports it on the first optimizer's construction (~0.9 s), which would stall a learner's
# first update while every actor waits for it.
PRELOAD = ["convoy.actors.actor", "convoy.algos.agent", "convoy.learner.service", "torch._dynamo"]
EXIT_GRACE_S = 3.0  # how long an actor's exit 0 waits for the learner's word that the job has its data
SHORT_LIFE_S = 10.0  # an actor that dies younger than this is crash-looping: its respawn backs off
MAX_BACKOFF_S = 30.0
log = logging.getLogger(__name__)


def pid_alive(pid: int | None) -> bool:
    """Whether ``pid`` is a live (not zombie) process."""
    if not pid:
        return False
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, PermissionError):
        return False
    try:
        return Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"
    except (OSError, IndexError):
        return True


def _context() -> Any:
    if "forkserver" not in mp.get_all_start_methods():
        return mp.get_context("spawn")
    ctx = mp.get_context("forkserver")
    ctx.set_forkserver_preload(PRELOAD)
    return ctx


_CTX = _context()


def _role_main(ident: str, reports: str | None, run: Callable[[], int]) -> None:
    """A role process: its log lines to stdout (the host's log), its errors also to the job's reports file, where
    the job service reads why it died; an uncaught exception is logged once (traceback and report), exit code 1."""
    setup_logging(reports, ident)
    try:
        code = run()
    except ConfigError as exc:  # the job's configuration, not this process: a respawn would refuse it again
        log.error("ConfigError: %s", exc)
        code = CONFIG
    except Exception:
        log.exception("%s died", ident)
        code = 1
    raise SystemExit(code)


def _actor_main(
    job_id: str, job: JobConfig, index: int, ident: str, settings: ZenohSettings, seed: int, reports: str | None
) -> None:
    from convoy.actors.actor import run_actor

    _role_main(ident, reports, lambda: run_actor(job_id, job, index, ident, settings, seed))


def _learner_main(job_id: str, job: JobConfig, out_dir: str, settings: ZenohSettings, ident: str,
                  reports: str | None, has_data: Any = None) -> None:  # fmt: skip
    """``has_data``: the group's event the learner sets once the job has its steps (``ProcessGroup.poll``)."""
    from convoy.learner.service import run_learner

    on_data = has_data.set if has_data is not None else None
    _role_main(ident, reports, lambda: run_learner(job_id, job, out_dir, settings, on_data))


@dataclass
class Slot:
    role: str
    index: int
    generation: int
    proc: Any
    started: float = field(default_factory=time.monotonic)

    prefix: str = ""
    exited_at: float | None = None  # when an exit 0 was first seen before the learner had the job's steps

    @property
    def ident(self) -> str:
        base = f"{self.prefix}{self.role}-{self.index}"
        return base if self.generation == 0 else f"{base}.{self.generation}"


@dataclass
class Event:
    kind: str  # "exited" | "crashed" | "backoff" | "respawned" | "failed"
    role: str
    ident: str
    detail: str = ""
    refused: bool = False  # "failed" because a process refused the job's configuration (exit code CONFIG)


class JobFailed(RuntimeError):
    """Too many crashes of one role: the job is given up, with the reason."""


class JobRefused(JobFailed):
    """A process refused the job's configuration (a ConfigError where it ran): the job never trained."""


class ProcessGroup:
    """The processes of one job on this machine."""

    def __init__(
        self,
        job_id: str,
        job: JobConfig,
        out_dir: str,
        settings: ZenohSettings,
        roles: tuple[str, ...] = ("learner", "actor"),
        host: str = "",
    ) -> None:
        """``host``: this machine's name in a multi-host job; it prefixes actor ids and salts their seeds, so actors
        of different hosts never share a key or a seed."""
        self.job_id, self.job, self.out_dir, self.settings, self.roles = job_id, job, out_dir, settings, roles
        self.reports = str(Path(out_dir) / REPORTS_FILE) if out_dir else None  # what its processes report
        self.host = host
        self.actors: dict[int, Slot] = {}
        self.respawn_at: dict[int, tuple[float, int]] = {}  # actor index → (when, generation) of a pending respawn
        self.short_lives: dict[int, int] = {}  # index → deaths within SHORT_LIFE_S of start in a row
        self.learner: Slot | None = None
        # set by this group's learner (a child: no peer on the job's keys can set it) once the job has its steps,
        # before it tells the actors so: their exit 0 after it is the job's end, not a crash, however long the
        # learner's final evaluation and last row take on a loaded machine
        self.has_data: Any = _CTX.Event() if "learner" in roles else None
        self.crashes: dict[str, deque[float]] = {"actor": deque(), "learner": deque()}
        self.finished: set[str] = set()  # roles whose processes exited 0
        self.failed: str | None = None

    # ----------------------------------------------------------------------------------------------- starting
    def _spawn_actor(self, index: int, generation: int) -> Slot:
        slot = Slot("actor", index, generation, None, prefix=f"{self.host}." if self.host else "")
        # distinct across hosts (the host name), indices and respawns: no two actors replay the same episodes
        seed = self.job.seed + 1000 * (index + 1) + 7919 * generation + (zlib.crc32(self.host.encode()) % 10**6) * 10**4
        # no shared memory for actors: a process that received from an actor keeps the actor's segments mapped
        # after it dies (~20 MiB each), so churn grew the learner without bound. Chunks are small and few (tens of
        # KB, tens per second); TCP loopback carries them at a fraction of its capacity.
        settings = self.settings.model_copy(update={"shared_memory": False})
        args = (self.job_id, self.job, index, slot.ident, settings, seed, self.reports)
        slot.proc = _CTX.Process(target=_actor_main, args=args, name=slot.ident, daemon=True)
        slot.proc.start()
        return slot

    def _spawn_learner(self, generation: int) -> Slot:
        slot = Slot("learner", 0, generation, None)
        args = (self.job_id, self.job, self.out_dir, self.settings, slot.ident, self.reports, self.has_data)
        slot.proc = _CTX.Process(target=_learner_main, args=args, name=slot.ident, daemon=True)
        slot.proc.start()
        return slot

    def start_learner(self) -> None:
        if self.learner is None:
            self.learner = self._spawn_learner(0)

    def scale_actors(self, n: int) -> None:
        """Start or stop actors until ``n`` run (highest indices stop first, with SIGTERM)."""
        if n < 0:
            raise ValueError(f"actors: must be ≥ 0 (got {n})")
        for index in range(n):
            if index not in self.actors and index not in self.respawn_at:
                self.actors[index] = self._spawn_actor(index, 0)
        for index in sorted(self.actors, reverse=True):
            if index >= n:
                self._terminate(self.actors.pop(index))
        for index in [i for i in self.respawn_at if i >= n]:
            del self.respawn_at[index]

    # ------------------------------------------------------------------------------------------------ watching
    def pids(self) -> dict[str, int]:
        """Every process of the group by id: what tests clean up by PID."""
        slots = list(self.actors.values()) + ([self.learner] if self.learner else [])
        return {s.ident: s.proc.pid for s in slots if s.proc is not None and s.proc.pid}

    def _crash(self, role: str, slot: Slot, code: int | None) -> Event | None:
        rt = self.job.runtime
        now = time.monotonic()
        window = self.crashes[role]
        window.append(now)
        while window and now - window[0] > rt.restart_window_s:
            window.popleft()
        field_name = "max_restarts" if role == "learner" else "actor_max_restarts"
        if len(window) > getattr(rt, field_name):
            self.failed = (
                f"{role} crashed {len(window)} times within {rt.restart_window_s:g} s "
                f"(last: {slot.ident} exit code {code}); see the job's log for the cause, or raise "
                f'runtime.{field_name} (convoy train --runtime {field_name}=N; REST: "runtime": '
                f'{{"{field_name}": N}}) or fix the cause'
            )
            return Event("failed", role, slot.ident, self.failed)
        return None

    def _refused(self, slot: Slot, code: int) -> Event:
        """``slot``'s process refused the job's configuration: the job fails, with the refusal it reported."""
        said = [r.detail for r in read_reports(self.reports, last=200) if r.kind == "error"
                and r.source == slot.ident] if self.reports else []  # fmt: skip
        why = said[-1] if said else "see the job's log for the refusal"
        self.failed = (
            f"{slot.ident} refused the job's configuration (exit code {code}), so it is not restarted: {why}; fix "
            "the config (or the file it names) and start the job again"
        )
        return Event("failed", slot.role, slot.ident, self.failed, refused=True)

    def _schedule_respawn(self, index: int, slot: Slot) -> float:
        """Respawn actor ``index`` at once after churn, after a doubling delay when it keeps dying at start."""
        now = time.monotonic()
        short = self.short_lives.get(index, 0) + 1 if now - slot.started < SHORT_LIFE_S else 0
        self.short_lives[index] = short
        delay = 0.0 if short == 0 else min(MAX_BACKOFF_S, self.job.runtime.restart_backoff_s * 2 ** (short - 1))
        self.respawn_at[index] = (now + delay, slot.generation + 1)
        return delay

    def _respawn_due(self) -> list[Event]:
        now, events = time.monotonic(), []
        for index, (when, generation) in sorted(self.respawn_at.items()):
            if when <= now:
                del self.respawn_at[index]
                self.actors[index] = self._spawn_actor(index, generation)
                events.append(Event("respawned", "actor", self.actors[index].ident))
        return events

    def poll(self, learner_has_data: bool = False) -> list[Event]:
        """Notice exits; respawn crashed actors, restart a crashed learner; returns what happened.

        An actor that exits 0 while this group's learner runs and has neither reported the job's steps
        (``learner_has_data``) nor told this group so (``has_data``, set before it tells the actors) left early — a
        stop or budget it was sent, forged or not — and is respawned like a crashed one: a job never waits on actors
        that are gone. Without a local learner (an actor-only host) exit 0
        is taken at its word.
        """
        events: list[Event] = []
        if self.failed:
            return events
        learner_has_data = learner_has_data or (self.has_data is not None and self.has_data.is_set())
        for index, slot in list(self.actors.items()):
            code = slot.proc.exitcode
            if code is None:
                continue
            slot.proc.join(0)
            learner = self.learner
            left_early = code == 0 and learner is not None and not learner_has_data
            if left_early and learner is not None and learner.proc.exitcode is None:
                # the learner tells actors it has all its data just before its last row: that row (or the learner's
                # own exit 0) may still be on its way. Wait for it a little before calling the exit a crash.
                slot.exited_at = slot.exited_at or time.monotonic()
                if time.monotonic() - slot.exited_at < EXIT_GRACE_S:
                    continue
            if left_early and learner is not None and learner.proc.exitcode == 0:
                left_early = False  # the learner finished: the actor left because the job has its data
            if code == 0 and not left_early:
                events.append(Event("exited", "actor", slot.ident))
                del self.actors[index]
                self.finished.add("actor")
                continue
            del self.actors[index]
            if code == CONFIG:
                return [*events, self._refused(slot, code)]
            if left_early:  # not a crash loop: not counted against actor_max_restarts
                events.append(Event("crashed", "actor", slot.ident, "exited before the learner had the job's steps"))
            else:
                events.append(Event("crashed", "actor", slot.ident, f"exit code {code}"))
                fail = self._crash("actor", slot, code)
                if fail:
                    return [*events, fail]
            delay = self._schedule_respawn(index, slot)
            if delay:
                short = self.short_lives[index]
                detail = f"died within {SHORT_LIFE_S:g} s of its start {short}× in a row; respawn in {delay:g} s"
                events.append(Event("backoff", "actor", slot.ident, detail))
        events += self._respawn_due()
        if self.learner is not None and self.learner.proc.exitcode is not None:
            slot, code = self.learner, self.learner.proc.exitcode
            slot.proc.join(0)
            if code == 0:
                events.append(Event("exited", "learner", slot.ident))
                self.finished.add("learner")
                self.learner = None
            elif code == DIVERGED:  # deterministic: the restarted learner would diverge the same way
                detail = (
                    f"{slot.ident} stopped: training diverged (non-finite losses in a row, exit code {code}); the "
                    "weights were kept finite. Lower lr (algo_params.lr) or check the env's rewards and observations"
                )
                self.learner = None
                return [*events, Event("failed", "learner", slot.ident, detail)]
            elif code == CONFIG:
                self.learner = None
                return [*events, self._refused(slot, code)]
            else:
                events.append(Event("crashed", "learner", slot.ident, f"exit code {code}"))
                fail = self._crash("learner", slot, code)
                if fail:
                    return [*events, fail]
                self.learner = self._spawn_learner(slot.generation + 1)
                events.append(Event("respawned", "learner", self.learner.ident, "resumes from its checkpoint"))
        return events

    # ------------------------------------------------------------------------------------------------ stopping
    @staticmethod
    def _terminate(slot: Slot) -> None:
        if slot.proc.is_alive():
            slot.proc.terminate()  # SIGTERM: actors stop, a learner checkpoints first

    def stop_all(self, timeout: float = 10.0) -> None:
        """SIGTERM everything, wait up to ``timeout``, then SIGKILL what is left (by PID)."""
        slots = list(self.actors.values()) + ([self.learner] if self.learner else [])
        for slot in slots:
            self._terminate(slot)
        deadline = time.monotonic() + timeout
        for slot in slots:
            slot.proc.join(max(0.0, deadline - time.monotonic()))
            if slot.proc.is_alive() and slot.proc.pid:
                os.kill(slot.proc.pid, signal.SIGKILL)
                slot.proc.join(2.0)
        self.actors.clear()
        self.respawn_at.clear()
        self.learner = None
