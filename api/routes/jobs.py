"""Jobs: submit, list, view, scale, stop, resume, delete; their logs, checkpoints and evaluation."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Depends, Query
from fastapi import Path as PathParam
from fastapi.responses import FileResponse, Response

from convoy.api.deps import JOB_ID, JobControl, authorised, control_of, view
from convoy.api.lifecycle import JobState
from convoy.api.models import (
    EvalRequest,
    EvaluationList,
    EvaluationView,
    JobList,
    JobPatch,
    JobResume,
    JobSubmit,
    JobView,
)
from convoy.output import json_safe

router = APIRouter(tags=["jobs"])
CONTROL = Depends(control_of)
AUTH = [Depends(authorised)]


@router.post("/jobs", status_code=201, response_model=JobView, tags=["jobs"], dependencies=AUTH)
def submit(body: JobSubmit, control: JobControl = CONTROL) -> JobView:
    return view(control.submit(body.job_config(), body.actors, body.name), control)


@router.get("/jobs", response_model=JobList, tags=["jobs"])
def list_jobs(state: JobState | None = None, control: JobControl = CONTROL) -> JobList:
    return JobList(jobs=[view(r, control) for r in control.store.list(state)])


@router.get("/jobs/{job_id}", response_model=JobView, tags=["jobs"])
def get_job(job_id: str = PathParam(..., pattern=JOB_ID), control: JobControl = CONTROL) -> JobView:
    return view(control.store.get(job_id), control)


@router.patch("/jobs/{job_id}", response_model=JobView, tags=["jobs"], dependencies=AUTH)
def scale(body: JobPatch, job_id: str = PathParam(..., pattern=JOB_ID), control: JobControl = CONTROL) -> JobView:
    return view(control.scale(job_id, body.actors), control)


@router.post("/jobs/{job_id}/stop", response_model=JobView, tags=["jobs"], dependencies=AUTH)
def stop(job_id: str = PathParam(..., pattern=JOB_ID), control: JobControl = CONTROL) -> JobView:
    return view(control.stop(job_id), control)


@router.post("/jobs/{job_id}/resume", response_model=JobView, tags=["jobs"], dependencies=AUTH)
def resume(
    body: JobResume | None = None, job_id: str = PathParam(..., pattern=JOB_ID), control: JobControl = CONTROL
) -> JobView:
    body = body or JobResume()
    return view(control.resume(job_id, body.actors, body.steps), control)


@router.delete("/jobs/{job_id}", status_code=204, tags=["jobs"], dependencies=AUTH)
def delete(job_id: str = PathParam(..., pattern=JOB_ID), control: JobControl = CONTROL) -> Response:
    control.delete(job_id)
    return Response(status_code=204)


@router.get("/jobs/{job_id}/logs", tags=["jobs"])
def logs(
    job_id: str = PathParam(..., pattern=JOB_ID),
    lines: int = Query(200, ge=1, le=10_000, description="How many of the last lines."),
    control: JobControl = CONTROL,
) -> dict[str, Any]:
    """The job's process logs (its host's log): starts, respawns, crashes and their tracebacks."""
    control.store.get(job_id)
    return {"job": job_id, "lines": control.logs(job_id, lines)}


@router.get("/jobs/{job_id}/checkpoints", tags=["checkpoints"])
def checkpoints(job_id: str = PathParam(..., pattern=JOB_ID), control: JobControl = CONTROL) -> dict[str, Any]:
    control.store.get(job_id)
    return {"job": job_id, "checkpoints": control.checkpoints(job_id)}


@router.get("/jobs/{job_id}/checkpoints/{name}", tags=["checkpoints"], response_class=FileResponse)
def download(
    job_id: str = PathParam(..., pattern=JOB_ID),
    name: str = PathParam(..., pattern=r"^[A-Za-z0-9_.-]{1,128}$"),
    control: JobControl = CONTROL,
) -> FileResponse:
    control.store.get(job_id)
    path = control.checkpoint_file(job_id, name)
    return FileResponse(path, media_type="application/octet-stream", filename=name)


@router.post("/jobs/{job_id}/evaluate", status_code=202, response_model=EvaluationView, tags=["jobs"],
             dependencies=AUTH)  # fmt: skip
def evaluate(
    body: EvalRequest, job_id: str = PathParam(..., pattern=JOB_ID), control: JobControl = CONTROL
) -> EvaluationView:
    """Start greedy episodes of the job's checkpoint in their own process; follow them at the evaluation's URL."""
    control.store.get(job_id)
    return EvaluationView(**json_safe(control.evaluate(job_id, body)))


@router.get("/jobs/{job_id}/evaluations", response_model=EvaluationList, tags=["jobs"])
def evaluations(job_id: str = PathParam(..., pattern=JOB_ID), control: JobControl = CONTROL) -> EvaluationList:
    control.store.get(job_id)
    return EvaluationList(evaluations=[EvaluationView(**json_safe(e)) for e in control.evaluations(job_id)])


@router.get("/jobs/{job_id}/evaluations/{eval_id}", response_model=EvaluationView, tags=["jobs"])
def evaluation(
    job_id: str = PathParam(..., pattern=JOB_ID),
    eval_id: str = PathParam(..., pattern=r"^[0-9a-f]{6}$"),
    control: JobControl = CONTROL,
) -> EvaluationView:
    control.store.get(job_id)
    return EvaluationView(**json_safe(control.evaluation(job_id, eval_id)))
