"""One error shape for every answer the API gives a caller's mistake: ``{"field", "problem", "fix"}`` with a 4xx.

The handlers turn FastAPI's validation errors, Starlette's routing errors, the config's ``ConfigError`` and the
store's refusals into that shape; ``BodyLimit`` refuses an over-large body before any route reads it; and
``ERROR_RESPONSES`` documents the real body for every status in the OpenAPI schema. A fix that names a request
(``api/remedy.py``) says it as the route, or as the convoy command when the request asked for ``Convoy-Words: cli``.
"""

from __future__ import annotations

import json
from typing import Any, cast

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match

from convoy.api.lifecycle import StoreError, UnknownEvaluation, UnknownJob, UnknownSweep
from convoy.api.models import ErrorBody
from convoy.api.remedy import WORDS_HEADER, ConfigRefusal, Fix, Step, words_of
from convoy.config import ConfigError

MAX_BODY = 64 * 1024


class ApiError(Exception):
    def __init__(self, status: int, field: str, problem: str, fix: str) -> None:
        super().__init__(problem)
        self.status, self.body = status, ErrorBody(field=field, problem=problem, fix=fix)


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


def said(request: Request, fix: Fix) -> str:
    """``fix`` in the words ``request`` asked for, for the job its path names (``/jobs/{job_id}…``)."""
    return fix.of_job(request.path_params.get("job_id")).say(words_of(request.headers.get(WORDS_HEADER)))


def _handler(status: int, field: str, fix: Fix) -> Any:
    """An exception handler answering ``status`` with the exception's message as the problem and its own ``fix``
    (a ``StoreError``'s), else ``fix``."""

    async def handle(request: Request, exc: Exception) -> JSONResponse:
        own = getattr(exc, "fix", None)
        return error_response(status, field, str(exc), said(request, own if isinstance(own, Fix) else fix))

    return handle


# What a ConfigError's caller does: change the field, whose default and range the catalogues list.
CONFIG_FIX = Fix("change this field ({} and {} list every parameter with its default and range)",
                 Step("GET /envs"), Step("GET /algos"))  # fmt: skip


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


def install_error_handlers(app: FastAPI) -> None:
    """Every error in the one shape, never a 5xx for the caller's mistakes."""

    @app.exception_handler(ApiError)
    async def _api_error(_: Request, exc: ApiError) -> JSONResponse:
        return JSONResponse(exc.body.model_dump(), status_code=exc.status)

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
        err = exc.errors()[0] if exc.errors() else {"loc": (), "msg": "invalid request"}
        loc = [str(p) for p in err.get("loc", ()) if p not in ("body", "query", "path")]
        field = ".".join(loc) or "body"
        if err.get("type") == "json_invalid":
            return error_response(400, "body", "the body is not valid JSON", "send a JSON object")
        ctx = cast(dict[str, Any], err.get("ctx") or {})
        if isinstance(ctx.get("error"), ConfigError):  # a model's own check: it names the field and the fix
            cause = ctx["error"]
            fix = said(request, cause.fix) if isinstance(cause, ConfigRefusal) else "change this field"
            return error_response(422, cause.field, str(cause).split(": ", 1)[-1], fix)
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
    async def _config(request: Request, exc: ConfigError) -> JSONResponse:
        text = str(exc).split(": ", 1)[-1]
        fix = exc.fix if isinstance(exc, ConfigRefusal) else CONFIG_FIX
        return error_response(422, exc.field, text, said(request, fix))

    # the store's and the files' errors: (status, field, fix); the most specific class wins (UnknownJob, then
    # StoreError for every other refusal, InvalidTransition included)
    for exc_type, (status, field, fix) in {
        UnknownJob: (404, "id", Fix("list the jobs with {}", Step("GET /jobs"))),
        UnknownSweep: (404, "id", Fix("list the sweeps with {}", Step("GET /sweeps"))),
        StoreError: (409, "state", Fix("check the job's state with {}", Step("GET /jobs/{id}"))),
        UnknownEvaluation: (404, "eval_id", Fix("list the evaluations with {}", Step("GET /jobs/{id}/evaluations"))),
        FileNotFoundError: (404, "name", Fix("list the files with {}", Step("GET /jobs/{id}/checkpoints"))),
    }.items():
        app.add_exception_handler(exc_type, _handler(status, field, fix))

    app.add_middleware(BodyLimit, limit=MAX_BODY)
