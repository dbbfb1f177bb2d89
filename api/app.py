"""The job service's HTTP face: FastAPI routes over a ``JobControl`` (what runs jobs) and the job store it reads
(``JobReader``).

The app only validates, authorises, reads the store and asks the control to act; it never starts a process itself
(``services.jobservice`` does; ``convoy serve`` passes it in — ``api`` imports the job config, the catalog and the
shared helpers, never the runtime: docs/architecture.md's import graph, tested). Every
error is JSON ``{"field", "problem", "fix"}`` with a 4xx status (``api/errors.py``); mutating routes need
``Authorization: Bearer <token>`` (``api/deps.py``); request bodies are capped at 64 KiB. The routes are
``api/routes/``: jobs, metrics, service, sweeps. Reads are cheap indexed queries of the SQLite store, so polling metrics
never touches, let alone stalls, the training processes.
"""

from __future__ import annotations

from typing import Any

from fastapi import FastAPI
from fastapi.staticfiles import StaticFiles

from convoy.api.deps import JobControl
from convoy.api.errors import ERROR_RESPONSES, install_error_handlers
from convoy.api.routes import jobs, metrics, service, sweeps
from convoy.api.routes.service import STATIC


def create_app(control: JobControl, token: str) -> FastAPI:
    """The FastAPI app over ``control``; ``token`` guards every mutating route."""
    app = FastAPI(
        title="Convoy job service",
        description="Submit, scale, stop and resume multi-agent training jobs; poll or stream their metrics.",
        version="1",
        responses=ERROR_RESPONSES,
    )
    app.state.control, app.state.token = control, token
    install_error_handlers(app)
    for module in (service, jobs, metrics, sweeps):
        app.include_router(module.router)
    if STATIC.is_dir():
        app.mount("/static", StaticFiles(directory=STATIC), name="static")
    _bound_actors_in_schema(app, control.max_processes - 2)
    return app


def _bound_actors_in_schema(app: FastAPI, limit: int) -> None:
    """Publish this server's actor limit (``--max-processes`` − 2) as the schema's maximum, so that every body the
    schema calls valid is one the server takes; larger values still get the 422 that names the flag."""
    default = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            schema = default()
            models = schema.get("components", {}).get("schemas", {})
            for name in ("JobSubmit", "JobPatch", "JobResume"):  # requests only: a view reports what a job has
                field = models[name]["properties"]["actors"]
                for variant in (field, *field.get("anyOf", ())):  # JobResume's is integer | null
                    if variant.get("type") == "integer":
                        variant["maximum"] = min(variant.get("maximum", limit), limit)
            app.openapi_schema = schema
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]  # FastAPI's documented hook for a custom schema
