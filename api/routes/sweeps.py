"""Sweeps: submit a grid of jobs, follow it, stop, resume or delete it, and read its summary with CIs."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Query
from fastapi import Path as PathParam
from fastapi.responses import Response

from convoy.api.deps import JOB_ID, JobControl, authorised, control_of
from convoy.api.models import SweepList, SweepSubmit, SweepSummary, SweepView
from convoy.api.sweeps import summarize, sweep_state, sweep_view
from convoy.output import json_safe

router = APIRouter(tags=["sweeps"])
CONTROL = Depends(control_of)
AUTH = [Depends(authorised)]
SWEEP_ID = PathParam(..., pattern=JOB_ID)


@router.post("/sweeps", status_code=201, response_model=SweepView, dependencies=AUTH)
def submit(body: SweepSubmit, control: JobControl = CONTROL) -> SweepView:
    """Queue every job of the grid; they run as the service's process budget allows, oldest first."""
    return sweep_view(control.submit_sweep(body), control.store)


@router.get("/sweeps", response_model=SweepList)
def list_sweeps(control: JobControl = CONTROL) -> SweepList:
    return SweepList(sweeps=[sweep_view(s, control.store) for s in control.store.sweeps()])


@router.get("/sweeps/{sweep_id}", response_model=SweepView)
def get_sweep(sweep_id: str = SWEEP_ID, control: JobControl = CONTROL) -> SweepView:
    return sweep_view(control.store.sweep(sweep_id), control.store)


@router.get("/sweeps/{sweep_id}/summary", response_model=SweepSummary)
def summary(
    sweep_id: str = SWEEP_ID,
    threshold: float | None = Query(None, description="Time to this return (default: the sweep's threshold)."),
    control: JobControl = CONTROL,
) -> SweepSummary:
    """Per group (the grid point without its seed): mean and 95 % CI over seeds of the greedy curve, the final
    greedy return and the time to the threshold."""
    sweep = control.store.sweep(sweep_id)
    limit = threshold if threshold is not None else sweep.spec.get("threshold")
    groups = json_safe(summarize(sweep.jobs, control.store, limit))
    states: dict[str, int] = {}
    for group in groups:  # the jobs were read once, for their curves; their states come with them
        for name, n in group["states"].items():
            states[name] = states.get(name, 0) + n
    return SweepSummary(id=sweep.id, state=sweep_state(states), threshold=limit, groups=groups)


@router.post("/sweeps/{sweep_id}/stop", response_model=SweepView, dependencies=AUTH)
def stop(sweep_id: str = SWEEP_ID, control: JobControl = CONTROL) -> SweepView:
    """Stop every queued or running job of the sweep (each checkpoints first)."""
    return sweep_view(control.stop_sweep(sweep_id), control.store)


@router.post("/sweeps/{sweep_id}/resume", response_model=SweepView, dependencies=AUTH)
def resume(sweep_id: str = SWEEP_ID, control: JobControl = CONTROL) -> SweepView:
    """Queue every stopped or failed job of the sweep again, from its last checkpoint."""
    return sweep_view(control.resume_sweep(sweep_id), control.store)


@router.delete("/sweeps/{sweep_id}", status_code=204, dependencies=AUTH)
def delete(sweep_id: str = SWEEP_ID, control: JobControl = CONTROL) -> Response:
    """Delete the sweep and every job of it, with their processes, histories and files."""
    control.delete_sweep(sweep_id)
    return Response(status_code=204)
