"""The job service's HTTP face: FastAPI routes over a ``JobControl`` (what runs jobs) and the ``JobStore``.

The app only validates, authorises, reads the store and asks the control to act; it never starts a process itself
(``services.jobservice`` does, the composition root passes it in — ``api`` imports nothing but ``protocol``). Every
error is JSON ``{"field", "problem", "fix"}`` with a 4xx status; mutating routes need ``Authorization: Bearer
<token>``; request bodies are capped at 64 KiB. Reads are cheap indexed queries of the SQLite store, so polling
metrics never touches, let alone stalls, the training processes.
"""

from __future__ import annotations

import asyncio
import json
import math
import secrets
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any, Protocol

from fastapi import Depends, FastAPI, Query, Request
from fastapi import Path as PathParam
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse, PlainTextResponse, Response, StreamingResponse
from fastapi.staticfiles import StaticFiles
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match

from api.models import (
    ErrorBody,
    EvalRequest,
    JobList,
    JobPatch,
    JobResume,
    JobSubmit,
    JobView,
    MetricsPage,
    Progress,
)
from api.store import FINAL_STATES, JobRecord, JobState, JobStore, StoreError, UnknownJob
from protocol.config import ConfigError, JobConfig

STATIC = Path(__file__).parent / "static"
MAX_BODY = 64 * 1024
PROGRESS_FIELDS = ("updates", "return", "loss", "env_steps_per_s", "updates_per_s", "policy_lag")
JOB_ID = r"^[A-Za-z0-9_.-]{1,64}$"


class JobControl(Protocol):
    """What the app needs from whoever runs jobs (``services.jobservice.JobService``)."""

    store: JobStore
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
    def logs(self, job_id: str, lines: int) -> list[str]: ...


class ApiError(Exception):
    def __init__(self, status: int, field: str, problem: str, fix: str) -> None:
        super().__init__(problem)
        self.status, self.body = status, ErrorBody(field=field, problem=problem, fix=fix)


def finite(value: Any) -> Any:
    """JSON has no NaN/inf: they travel as null."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: finite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [finite(v) for v in value]
    return value


class BodyLimit:
    """ASGI middleware: a request body over ``limit`` bytes is answered 413 before any route reads it — declared
    (``Content-Length``) or not (chunked: counted while buffered; bodies here are small JSON)."""

    def __init__(self, app: Any, limit: int) -> None:
        self.app, self.limit = app, limit

    async def __call__(self, scope: dict[str, Any], receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = dict(scope.get("headers", ())).get(b"content-length")
        if declared is not None and not declared.isdigit():
            await self._refuse(send, 400, "Content-Length is not a number", "send a valid Content-Length")
            return
        if declared is not None and int(declared) > self.limit:
            await self._refuse(send, 413, f"larger than {self.limit} bytes", "send a smaller body")
            return
        messages, total = [], 0
        while True:
            message = await receive()
            messages.append(message)
            if message["type"] != "http.request":
                break
            total += len(message.get("body", b""))
            if total > self.limit:
                await self._refuse(send, 413, f"larger than {self.limit} bytes", "send a smaller body")
                return
            if not message.get("more_body", False):
                break

        async def replay() -> dict[str, Any]:
            return messages.pop(0) if messages else await receive()

        await self.app(scope, replay, send)

    @staticmethod
    async def _refuse(send: Any, status: int, problem: str, fix: str) -> None:
        body = json.dumps({"field": "body", "problem": problem, "fix": fix}).encode()
        headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
        await send({"type": "http.response.start", "status": status, "headers": headers})
        await send({"type": "http.response.body", "body": body})


def error_response(status: int, field: str, problem: str, fix: str) -> JSONResponse:
    return JSONResponse(ErrorBody(field=field, problem=problem, fix=fix).model_dump(), status_code=status)


def _handler(status: int, field: str, fix: str) -> Any:
    """An exception handler answering ``status`` with the exception's message as the problem."""

    async def handle(_: Request, exc: Exception) -> JSONResponse:
        return error_response(status, field, str(exc), fix)

    return handle


# Every error any route can answer, documented with the body it really has (FastAPI would otherwise document its
# own 422 shape, which this server never sends).
ERROR_RESPONSES: dict[int | str, dict[str, Any]] = {
    status: {"model": ErrorBody, "description": what}
    for status, what in {
        400: "The body is not valid JSON.",
        401: "Missing or wrong bearer token (mutating routes).",
        404: "No such job, file or route.",
        405: "The route does not take this method.",
        409: "The job's state does not allow this.",
        413: "The body is too large.",
        422: "A field is out of range or unknown; `field` names it and `fix` says what to give.",
    }.items()
}


def create_app(control: JobControl, token: str) -> FastAPI:
    """The FastAPI app over ``control``; ``token`` guards every mutating route."""
    app = FastAPI(
        title="Convoy job service",
        description="Submit, scale, stop and resume multi-agent training jobs; poll or stream their metrics.",
        version="1",
        responses=ERROR_RESPONSES,
    )
    store = control.store

    # --- errors: one JSON shape, never a 5xx for the caller's mistakes ------------------------------------------
    @app.exception_handler(ApiError)
    async def _api_error(_: Request, exc: ApiError) -> JSONResponse:
        return JSONResponse(exc.body.model_dump(), status_code=exc.status)

    @app.exception_handler(RequestValidationError)
    async def _invalid(_: Request, exc: RequestValidationError) -> JSONResponse:
        err = exc.errors()[0] if exc.errors() else {"loc": (), "msg": "invalid request"}
        loc = [str(p) for p in err.get("loc", ()) if p not in ("body", "query", "path")]
        field = ".".join(loc) or "body"
        if err.get("type") == "json_invalid":
            return error_response(400, "body", "the body is not valid JSON", "send a JSON object")
        ctx = err.get("ctx") or {}
        words = {"ge": "≥", "gt": ">", "le": "≤", "lt": "<", "pattern": "matching", "expected": "one of"}
        bound = " and ".join(f"{words[k]} {v}" for k, v in ctx.items() if k in words)
        fix = f"give {field} {bound}" if bound else "see the schema at /docs"
        return error_response(422, field, str(err.get("msg", "invalid")), fix)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        """Starlette's own errors (no such route, wrong method, a malformed request) in the one shape."""
        fixes = {404: ("path", "see the routes at /docs"), 405: ("method", "see the methods each route takes at /docs")}
        field, fix = fixes.get(exc.status_code, ("request", "see the schema at /docs"))
        headers = getattr(exc, "headers", None)
        if exc.status_code == 405:  # Starlette names the first matching route's methods; a path may have several
            headers = {**(headers or {}), "Allow": ", ".join(_allowed_methods(request))}
        body = ErrorBody(field=field, problem=str(exc.detail), fix=fix).model_dump()
        return JSONResponse(body, status_code=exc.status_code, headers=headers)

    def _allowed_methods(request: Request) -> list[str]:
        methods: set[str] = set()
        for route in app.router.routes:
            match, _ = route.matches({**request.scope, "method": "GET"})
            if match != Match.NONE:
                methods |= set(getattr(route, "methods", None) or ())
        return sorted(methods - {"HEAD"})

    @app.exception_handler(ConfigError)
    async def _config(_: Request, exc: ConfigError) -> JSONResponse:
        text = str(exc).split(": ", 1)[-1]
        return error_response(422, exc.field, text, "change this field (GET /docs lists every parameter)")

    # the store's and the files' errors: (status, field, fix); the most specific class wins (UnknownJob, then
    # StoreError for every other refusal, InvalidTransition included)
    for exc_type, (status, field, fix) in {
        UnknownJob: (404, "id", "list the jobs with GET /jobs"),
        StoreError: (409, "state", "check the job's state with GET /jobs/{id}"),
        FileNotFoundError: (404, "name", "list the files with GET /jobs/{id}/checkpoints"),
    }.items():
        app.add_exception_handler(exc_type, _handler(status, field, fix))

    app.add_middleware(BodyLimit, limit=MAX_BODY)

    def authorised(request: Request) -> None:
        header = request.headers.get("authorization", "")
        scheme, _, given = header.partition(" ")
        if scheme.lower() != "bearer" or not secrets.compare_digest(given.strip().encode(), token.encode()):
            raise ApiError(
                401,
                "Authorization",
                "missing or wrong bearer token",
                "send 'Authorization: Bearer <token>' (printed by `convoy serve`, or set CONVOY_API_TOKEN)",
            )

    def view(rec: JobRecord) -> JobView:
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
                **{k: finite(prog.get(k)) for k in PROGRESS_FIELDS},
                dropped=prog.get("dropped") or {},
            ),
            created_at=rec.created_at,
            updated_at=rec.updated_at,
            error=rec.error,
            last_checkpoint=rec.last_checkpoint,
            queue_position=store.queue_position(rec.id),
            config=finite(cfg),
        )

    # --- routes --------------------------------------------------------------------------------------------------
    @app.get("/healthz", tags=["service"])
    def healthz() -> dict[str, Any]:
        return {"ok": True, "jobs": store.count_by_state()}

    @app.post("/jobs", status_code=201, response_model=JobView, tags=["jobs"], dependencies=[Depends(authorised)])
    def submit(body: JobSubmit) -> JobView:
        return view(control.submit(body.job_config(), body.actors, body.name))

    @app.get("/jobs", response_model=JobList, tags=["jobs"])
    def list_jobs(state: JobState | None = None) -> JobList:
        return JobList(jobs=[view(r) for r in store.list(state)])

    @app.get("/jobs/{job_id}", response_model=JobView, tags=["jobs"])
    def get_job(job_id: str = PathParam(..., pattern=JOB_ID)) -> JobView:
        return view(store.get(job_id))

    @app.patch("/jobs/{job_id}", response_model=JobView, tags=["jobs"], dependencies=[Depends(authorised)])
    def scale(body: JobPatch, job_id: str = PathParam(..., pattern=JOB_ID)) -> JobView:
        return view(control.scale(job_id, body.actors))

    @app.post("/jobs/{job_id}/stop", response_model=JobView, tags=["jobs"], dependencies=[Depends(authorised)])
    def stop(job_id: str = PathParam(..., pattern=JOB_ID)) -> JobView:
        return view(control.stop(job_id))

    @app.post("/jobs/{job_id}/resume", response_model=JobView, tags=["jobs"], dependencies=[Depends(authorised)])
    def resume(body: JobResume | None = None, job_id: str = PathParam(..., pattern=JOB_ID)) -> JobView:
        body = body or JobResume()
        return view(control.resume(job_id, body.actors, body.steps))

    @app.delete("/jobs/{job_id}", status_code=204, tags=["jobs"], dependencies=[Depends(authorised)])
    def delete(job_id: str = PathParam(..., pattern=JOB_ID)) -> Response:
        control.delete(job_id)
        return Response(status_code=204)

    @app.get("/jobs/{job_id}/metrics", response_model=MetricsPage, tags=["metrics"])
    def metrics(
        job_id: str = PathParam(..., pattern=JOB_ID),
        since: int | None = Query(None, ge=-1, le=2**62, description="Rows with env_steps > since."),
        names: str | None = Query(None, max_length=1000, description="Comma-separated metric names."),
        limit: int | None = Query(None, ge=1, le=100_000),
    ) -> MetricsPage:
        wanted = [n.strip() for n in names.split(",") if n.strip()] if names else None
        rows = store.metrics(job_id, since=since, names=wanted, limit=limit)
        last = rows[-1]["env_steps"] if rows else store.last_step(job_id)
        return MetricsPage(job=job_id, rows=finite(rows), last_step=last)

    @app.get("/jobs/{job_id}/events", tags=["metrics"], response_class=StreamingResponse)
    async def events(
        job_id: str = PathParam(..., pattern=JOB_ID),
        since: int | None = Query(None, ge=-1, le=2**62),
        timeout: float = Query(300.0, gt=0, le=3600, description="Seconds before the stream closes."),
    ) -> StreamingResponse:
        store.get(job_id)  # 404 before the stream starts

        async def stream() -> AsyncIterator[str]:
            last, state, t_end = since, None, time.monotonic() + timeout
            while time.monotonic() < t_end:
                rec = store.get(job_id) if store.exists(job_id) else None
                if rec is None:
                    yield "event: deleted\ndata: {}\n\n"
                    return
                rows = store.metrics(job_id, since=last)
                if rows:
                    last = rows[-1]["env_steps"]
                    yield f"event: metrics\ndata: {json.dumps(finite(rows))}\n\n"
                if rec.state != state:
                    state = rec.state
                    yield f"event: state\ndata: {json.dumps({'state': str(state), 'error': rec.error})}\n\n"
                    if state in FINAL_STATES:
                        return
                await asyncio.sleep(0.5)

        return StreamingResponse(stream(), media_type="text/event-stream")

    @app.get("/jobs/{job_id}/logs", tags=["jobs"])
    def logs(
        job_id: str = PathParam(..., pattern=JOB_ID),
        lines: int = Query(200, ge=1, le=10_000, description="How many of the last lines."),
    ) -> dict[str, Any]:
        """The job's process logs (its host's log): starts, respawns, crashes and their tracebacks."""
        store.get(job_id)
        return {"job": job_id, "lines": control.logs(job_id, lines)}

    @app.get("/jobs/{job_id}/checkpoints", tags=["checkpoints"])
    def checkpoints(job_id: str = PathParam(..., pattern=JOB_ID)) -> dict[str, Any]:
        store.get(job_id)
        return {"job": job_id, "checkpoints": control.checkpoints(job_id)}

    @app.get("/jobs/{job_id}/checkpoints/{name}", tags=["checkpoints"], response_class=FileResponse)
    def download(
        job_id: str = PathParam(..., pattern=JOB_ID),
        name: str = PathParam(..., pattern=r"^[A-Za-z0-9_.-]{1,128}$"),
    ) -> FileResponse:
        store.get(job_id)
        path = control.checkpoint_file(job_id, name)
        return FileResponse(path, media_type="application/octet-stream", filename=name)

    @app.post("/jobs/{job_id}/evaluate", tags=["jobs"], dependencies=[Depends(authorised)])
    def evaluate(body: EvalRequest, job_id: str = PathParam(..., pattern=JOB_ID)) -> dict[str, Any]:
        store.get(job_id)
        return finite(control.evaluate(job_id, body))

    @app.get("/metrics", tags=["service"], response_class=PlainTextResponse)
    def prometheus() -> PlainTextResponse:
        from api.prometheus import exposition

        text, content_type = exposition(store, control)
        return PlainTextResponse(text, media_type=content_type)

    @app.get("/", include_in_schema=False)
    def dashboard() -> Response:
        index = STATIC / "index.html"
        if not index.is_file():
            return PlainTextResponse("dashboard assets missing", status_code=404)
        return FileResponse(index, media_type="text/html")

    if STATIC.is_dir():
        app.mount("/static", StaticFiles(directory=STATIC), name="static")
    app.state.control = control
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
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]
