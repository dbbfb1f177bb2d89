"""Local process management for one job: start, respawn, scale and stop actor and learner processes.

Used by the job runner of ``convoy train`` and by host agents (``convoy host``) alike. Processes start from a
*forkserver* that has imported what every role needs (torch, the envs, the algorithms) once and never opens a Zenoh
session: a role process is a fork of it, so the job's processes do not each spend ~1.5 s of CPU importing torch side
by side at start-up, and a crashed actor is back in a fraction of a second. Forking the job's own process is not an
option (fork after a Zenoh session is open loses every message); where the platform has no forkserver the ``spawn``
method is used. Processes get plain-data arguments (job config, Zenoh settings) and are tracked by PID. A crashed
actor is respawned under a new id (its seed advanced, so it does not replay the same episodes); a crashed learner is
restarted and resumes from its checkpoint; more than ``max_restarts`` crashes of one role within
``restart_window_s`` fail the job with the reason. Exit code 0 means a process finished its part of the job and is
not restarted.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
import time
import zlib
from collections import deque
from dataclasses import dataclass, field
from typing import Any

from protocol.config import JobConfig
from protocol.session import ZenohSettings

# What the forkserver imports before it forks any role process (no Zenoh session, no torch op, no CUDA there).
# torch._dynamo: torch imports it on the first optimizer's construction (~0.9 s), which would stall a learner's
# first update while every actor waits for it.
PRELOAD = ["actors.actor", "learner.agent", "learner.service", "torch._dynamo"]


def _context() -> Any:
    if "forkserver" not in mp.get_all_start_methods():
        return mp.get_context("spawn")
    ctx = mp.get_context("forkserver")
    ctx.set_forkserver_preload(PRELOAD)
    return ctx


_CTX = _context()


def _actor_main(job_id: str, job: JobConfig, index: int, ident: str, settings: ZenohSettings, seed: int) -> None:
    from actors.actor import run_actor

    raise SystemExit(run_actor(job_id, job, index, ident, settings, seed))


def _learner_main(job_id: str, job: JobConfig, out_dir: str, settings: ZenohSettings) -> None:
    from learner.service import run_learner

    raise SystemExit(run_learner(job_id, job, out_dir, settings))


@dataclass
class Slot:
    role: str
    index: int
    generation: int
    proc: Any
    started: float = field(default_factory=time.monotonic)

    prefix: str = ""

    @property
    def ident(self) -> str:
        base = f"{self.prefix}{self.role}-{self.index}"
        return base if self.generation == 0 else f"{base}.{self.generation}"


@dataclass
class Event:
    kind: str  # "exited" | "crashed" | "respawned" | "failed"
    role: str
    ident: str
    detail: str = ""


class JobFailed(RuntimeError):
    """Too many crashes of one role: the job is given up, with the reason."""


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
        self.host = host
        self.actors: dict[int, Slot] = {}
        self.learner: Slot | None = None
        self.crashes: dict[str, deque[float]] = {"actor": deque(), "learner": deque()}
        self.finished: set[str] = set()  # roles whose processes exited 0
        self.failed: str | None = None

    # ----------------------------------------------------------------------------------------------- starting
    def _spawn_actor(self, index: int, generation: int) -> Slot:
        slot = Slot("actor", index, generation, None, prefix=f"{self.host}." if self.host else "")
        # distinct across hosts (the host name), indices and respawns: no two actors replay the same episodes
        seed = self.job.seed + 1000 * (index + 1) + 7919 * generation + (zlib.crc32(self.host.encode()) % 10**6) * 10**4
        args = (self.job_id, self.job, index, slot.ident, self.settings, seed)
        slot.proc = _CTX.Process(target=_actor_main, args=args, name=slot.ident, daemon=True)
        slot.proc.start()
        return slot

    def _spawn_learner(self, generation: int) -> Slot:
        slot = Slot("learner", 0, generation, None)
        args = (self.job_id, self.job, self.out_dir, self.settings)
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
            if index not in self.actors:
                self.actors[index] = self._spawn_actor(index, 0)
        for index in sorted(self.actors, reverse=True):
            if index >= n:
                self._terminate(self.actors.pop(index))

    # ------------------------------------------------------------------------------------------------ watching
    def pids(self) -> dict[str, int]:
        """Every process of the group by id: what tests clean up by PID."""
        slots = list(self.actors.values()) + ([self.learner] if self.learner else [])
        return {s.ident: s.proc.pid for s in slots if s.proc is not None and s.proc.pid}

    def _crash(self, role: str, slot: Slot, code: int | None) -> Event | None:
        now = time.monotonic()
        window = self.crashes[role]
        window.append(now)
        while window and now - window[0] > self.job.runtime.restart_window_s:
            window.popleft()
        if len(window) > self.job.runtime.max_restarts:
            self.failed = (
                f"{role} crashed {len(window)} times within {self.job.runtime.restart_window_s:g} s "
                f"(last: {slot.ident} exit code {code}); raise runtime.max_restarts or fix the cause"
            )
            return Event("failed", role, slot.ident, self.failed)
        return None

    def poll(self, learner_has_data: bool = False) -> list[Event]:
        """Notice exits; respawn crashed actors, restart a crashed learner; returns what happened.

        An actor that exits 0 while this group's learner runs and has not reported the job's steps
        (``learner_has_data``) left early — a stop or budget it was sent, forged or not — and is respawned like a
        crashed one: a job never waits on actors that are gone. Without a local learner (an actor-only host) exit 0
        is taken at its word.
        """
        events: list[Event] = []
        if self.failed:
            return events
        for index, slot in list(self.actors.items()):
            code = slot.proc.exitcode
            if code is None:
                continue
            slot.proc.join(0)
            left_early = code == 0 and self.learner is not None and not learner_has_data
            if code == 0 and not left_early:
                events.append(Event("exited", "actor", slot.ident))
                del self.actors[index]
                self.finished.add("actor")
                continue
            if left_early:  # not a crash loop: not counted against max_restarts
                events.append(Event("crashed", "actor", slot.ident, "exited before the learner had the job's steps"))
            else:
                events.append(Event("crashed", "actor", slot.ident, f"exit code {code}"))
                fail = self._crash("actor", slot, code)
                if fail:
                    return [*events, fail]
            self.actors[index] = self._spawn_actor(index, slot.generation + 1)
            events.append(Event("respawned", "actor", self.actors[index].ident))
        if self.learner is not None and self.learner.proc.exitcode is not None:
            slot, code = self.learner, self.learner.proc.exitcode
            slot.proc.join(0)
            if code == 0:
                events.append(Event("exited", "learner", slot.ident))
                self.finished.add("learner")
                self.learner = None
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
        self.learner = None
