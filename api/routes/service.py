"""The service itself: its health, the env and algorithm catalogues (``/envs``, ``/algos``) and the dashboard."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from fastapi import APIRouter, Depends
from fastapi.responses import FileResponse, PlainTextResponse, Response

from convoy.api.deps import JobControl, control_of

router = APIRouter()
CONTROL = Depends(control_of)
STATIC = Path(__file__).resolve().parents[1] / "static"


@router.get("/healthz", tags=["service"])
def healthz(control: JobControl = CONTROL) -> dict[str, Any]:
    return {"ok": True, "jobs": control.store.count_by_state()}


@router.get("/envs", tags=["service"])
def list_envs() -> dict[str, Any]:
    """Every environment with its parameters (a job's ``env_params``): default, allowed range, meaning."""
    from convoy.catalog import envs

    return {"envs": envs()}


@router.get("/algos", tags=["service"])
def list_algos() -> dict[str, Any]:
    """Every algorithm with its hyper-parameters (a job's ``algo_params``) and the values each env sets."""
    from convoy.catalog import algos

    return {"algos": algos()}


@router.get("/", include_in_schema=False)
def dashboard() -> Response:
    index = STATIC / "index.html"
    if not index.is_file():
        return PlainTextResponse("dashboard assets missing", status_code=404)
    return FileResponse(index, media_type="text/html")
