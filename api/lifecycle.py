"""A job's lifecycle as the API and the job service both speak it: its states, their allowed moves, the record of a
job, the errors of the store and what the API reads from it (``JobReader``). The SQLite store that writes all of
this lives beside the job service that drives it (``services/store.py``).

States and transitions
----------------------
``queued → starting → running → completed`` is the happy path. The allowed moves (``ALLOWED_TRANSITIONS``):

==========  ===============================  =====================================================================
from        to                               why
==========  ===============================  =====================================================================
queued      starting, stopped                launched by the scheduler; or cancelled before it ever started
starting    running, failed, stopping        came up; crashed while starting; stop asked during start-up
running     stopping, completed, failed      stop asked; reached its step budget; crashed
stopping    stopped, failed, completed       stopped cleanly; crashed while stopping; finished before the stop
stopped     queued                           resume (from its last checkpoint)
failed      queued                           resume after a crash (from its last checkpoint)
completed   queued                           resume to continue training past the old budget
==========  ===============================  =====================================================================

Nothing moves to its own state (a second stop of a stopping job is the API's business, not a transition). After an
API restart the jobs left in ``starting``/``running``/``stopping`` can be reconciled with ``→ failed`` (or
``stopping → stopped``); ``queued`` jobs simply stay queued. ``create`` records a first transition with
``from_state=None`` so the history starts at the job's birth. Moving to ``failed`` stores the reason as the job's
``error``; moving to ``queued`` clears it.
"""

from __future__ import annotations

import builtins
import json
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any, Protocol

from convoy.api.remedy import Fix


class JobState(StrEnum):
    """A job's lifecycle state; a ``str`` so it compares equal to, and serialises as, its name."""

    queued = "queued"
    starting = "starting"
    running = "running"
    stopping = "stopping"
    stopped = "stopped"
    completed = "completed"
    failed = "failed"


ALLOWED_TRANSITIONS: dict[JobState, frozenset[JobState]] = {
    JobState.queued: frozenset({JobState.starting, JobState.stopped}),
    JobState.starting: frozenset({JobState.running, JobState.failed, JobState.stopping}),
    JobState.running: frozenset({JobState.stopping, JobState.completed, JobState.failed}),
    JobState.stopping: frozenset({JobState.stopped, JobState.failed, JobState.completed}),
    JobState.stopped: frozenset({JobState.queued}),
    JobState.failed: frozenset({JobState.queued}),
    JobState.completed: frozenset({JobState.queued}),
}
"""Where each state may go next; see the module docstring for why."""

ACTIVE_STATES: frozenset[JobState] = frozenset(
    {JobState.queued, JobState.starting, JobState.running, JobState.stopping}
)
"""States in which a job holds (or waits for) resources."""

FINAL_STATES: frozenset[JobState] = frozenset({JobState.stopped, JobState.completed, JobState.failed})
"""States a job rests in until someone resumes or deletes it."""

_STATE_ORDER: tuple[JobState, ...] = tuple(JobState)


class StoreError(ValueError):
    """Anything the caller asked for that the store cannot do; the message says what, ``fix`` (when it is not the
    API's usual "check the job's state") what to do instead."""

    def __init__(self, message: str, fix: Fix | None = None) -> None:
        super().__init__(message)
        self.fix = fix


class UnknownJob(StoreError):
    """The job id is not in the store (the API maps this to 404)."""

    def __init__(self, job_id: str) -> None:
        self.job_id = job_id
        super().__init__(f"job {job_id!r} not found")


class UnknownSweep(StoreError):
    """The sweep id is not in the store (the API maps this to 404)."""

    def __init__(self, sweep_id: str) -> None:
        self.sweep_id = sweep_id
        super().__init__(f"sweep {sweep_id!r} not found")


class UnknownEvaluation(FileNotFoundError):
    """No evaluation of that id for the job (the API maps this to 404)."""


@dataclass(frozen=True)
class SweepRecord:
    """One sweep as stored: its request (``spec``) and its jobs in grid order, each ``{"id", "point"}``."""

    id: str
    created_at: float
    spec: dict[str, Any]
    jobs: list[dict[str, Any]]


class InvalidTransition(StoreError):
    """A state change the transition table does not allow (the API maps this to 409)."""

    def __init__(self, job_id: str, current: JobState, requested: JobState) -> None:
        self.job_id = job_id
        self.current = current
        self.requested = requested
        self.allowed = tuple(s for s in _STATE_ORDER if s in ALLOWED_TRANSITIONS[current])
        allowed = ", ".join(s.value for s in self.allowed) or "nothing"
        super().__init__(
            f"job {job_id!r} is {current.value}; it cannot move to {requested.value} "
            f"(allowed from {current.value}: {allowed})"
        )


@dataclass(frozen=True)
class JobRecord:
    """One job as stored; a snapshot — later changes to the store do not alter it."""

    id: str
    state: JobState
    config: dict[str, Any]
    actors: int
    created_at: float
    updated_at: float
    out_dir: str | None = None
    error: str | None = None
    last_checkpoint: str | None = None
    progress: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        """A plain dict for JSON responses, with the state as its string (non-finite floats are left as they are)."""
        return {
            "id": self.id,
            "state": self.state.value,
            "config": json.loads(json.dumps(self.config)),
            "actors": self.actors,
            "created_at": self.created_at,
            "updated_at": self.updated_at,
            "out_dir": self.out_dir,
            "error": self.error,
            "last_checkpoint": self.last_checkpoint,
            "progress": json.loads(json.dumps(self.progress)),
        }


class JobReader(Protocol):
    """The reads the API makes of the job store (``services.store.JobStore`` implements them)."""

    def get(self, job_id: str) -> JobRecord: ...
    def exists(self, job_id: str) -> bool: ...
    def list(self, state: JobState | str | None = None) -> builtins.list[JobRecord]: ...
    def queue_position(self, job_id: str) -> int | None: ...
    def count_by_state(self) -> dict[str, int]: ...
    def metrics(
        self, job_id: str, since: int | None = None, names: builtins.list[str] | None = None, limit: int | None = None
    ) -> builtins.list[dict[str, Any]]: ...
    def last_step(self, job_id: str) -> int | None: ...
    def sweep(self, sweep_id: str) -> SweepRecord: ...
    def sweeps(self) -> builtins.list[SweepRecord]: ...
