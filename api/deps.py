"""What every route needs: the job control and store of this app, the bearer-token check, and a job's view.

The composition root (``create_app``) keeps the control and the token in ``app.state``; routes take them through
FastAPI dependencies, so each route module is a plain ``APIRouter``.
"""

from __future__ import annotations

import secrets
from pathlib import Path
from typing import Any, Protocol

from fastapi import Request

from convoy.api.errors import ApiError
from convoy.api.lifecycle import JobReader, JobRecord, JobState, SweepRecord
from convoy.api.models import EvalRequest, FinalEvaluation, JobView, Progress, SweepSubmit
from convoy.api.remedy import WORDS_HEADER, words_of
from convoy.config import JobConfig
from convoy.output import json_safe

PROGRESS_FIELDS = ("updates", "return", "eval_return", "loss", "env_steps_per_s", "updates_per_s", "policy_lag",
                   "demo_round", "demo_rounds")  # fmt: skip
JOB_ID = r"^[A-Za-z0-9_.-]{1,64}$"


class JobControl(Protocol):
    """What the app needs from whoever runs jobs (``services.jobservice.JobService``)."""

    @property
    def store(self) -> JobReader: ...

    max_processes: int  # a job takes actors + 2: the schema's bound on actors follows it

    def submit(self, job: JobConfig, actors: int, name: str | None) -> JobRecord: ...
    def scale(self, job_id: str, actors: int) -> JobRecord: ...
    def stop(self, job_id: str) -> JobRecord: ...
    def resume(self, job_id: str, actors: int | None, steps: int | None) -> JobRecord: ...
    def delete(self, job_id: str) -> None: ...
    def actors_alive(self, job_id: str) -> int: ...
    def checkpoints(self, job_id: str) -> list[dict[str, Any]]: ...
    def checkpoint_file(self, job_id: str, name: str) -> Path: ...
    def evaluate(self, job_id: str, request: EvalRequest) -> dict[str, Any]: ...
    def evaluations(self, job_id: str) -> list[dict[str, Any]]: ...
    def evaluation(self, job_id: str, eval_id: str) -> dict[str, Any]: ...
    def logs(self, job_id: str, lines: int) -> list[str]: ...
    def submit_sweep(self, spec: SweepSubmit) -> SweepRecord: ...
    def stop_sweep(self, sweep_id: str) -> SweepRecord: ...
    def resume_sweep(self, sweep_id: str) -> SweepRecord: ...
    def delete_sweep(self, sweep_id: str) -> None: ...


def control_of(request: Request) -> JobControl:
    """The job control this app serves."""
    return request.app.state.control


def authorised(request: Request) -> None:
    """Mutating routes: a 401 in the one error shape unless the request carries this app's bearer token."""
    token: str = request.app.state.token
    header = request.headers.get("authorization", "")
    scheme, _, given = header.partition(" ")
    if scheme.lower() != "bearer" or not secrets.compare_digest(given.strip().encode(), token.encode()):
        api_fix = "send 'Authorization: Bearer <token>' (printed by `convoy serve`, or set CONVOY_API_TOKEN)"
        cli_fix = "pass --token TOKEN (printed by `convoy serve`) or set CONVOY_API_TOKEN"
        fix = cli_fix if words_of(request.headers.get(WORDS_HEADER)) == "cli" else api_fix
        raise ApiError(401, "Authorization", "missing or wrong bearer token", fix)


def view(rec: JobRecord, control: JobControl) -> JobView:
    """A job as ``GET /jobs/{id}`` shows it: its record, progress and live actor count."""
    cfg, prog = rec.config, rec.progress
    steps = int(cfg.get("steps", 0)) or 1
    env_steps = int(prog.get("env_steps", 0) or 0)
    active = rec.state in (JobState.starting, JobState.running, JobState.stopping)
    return JobView(
        id=rec.id,
        state=str(rec.state),
        algo=str(cfg.get("algo", "")),
        env=str(cfg.get("env", "")),
        actors=rec.actors,
        actors_alive=control.actors_alive(rec.id) if active else 0,
        steps=steps,
        progress=Progress(
            env_steps=env_steps,
            fraction=min(1.0, env_steps / steps),
            **{k: json_safe(prog.get(k)) for k in PROGRESS_FIELDS},
            dropped=prog.get("dropped") or {},
        ),
        created_at=rec.created_at,
        updated_at=rec.updated_at,
        error=rec.error,
        last_checkpoint=rec.last_checkpoint,
        queue_position=control.store.queue_position(rec.id),
        config=json_safe(cfg),
        final=FinalEvaluation(**json_safe(prog["final"])) if isinstance(prog.get("final"), dict) else None,
        population=prog.get("packed_in"),
        members=list(prog.get("members", [])),
    )
