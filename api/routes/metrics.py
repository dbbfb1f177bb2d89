"""Metrics: a job's rows (paged), a live stream of them (server-sent events), and Prometheus for the service."""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import AsyncIterator

from fastapi import APIRouter, Depends, Header, Query
from fastapi import Path as PathParam
from fastapi.responses import PlainTextResponse, StreamingResponse

from convoy.api.deps import JOB_ID, JobControl, control_of
from convoy.api.errors import ApiError
from convoy.api.lifecycle import FINAL_STATES
from convoy.api.models import MetricsPage
from convoy.output import json_safe

router = APIRouter()
CONTROL = Depends(control_of)


@router.get("/jobs/{job_id}/metrics", response_model=MetricsPage, tags=["metrics"])
def metrics(
    job_id: str = PathParam(..., pattern=JOB_ID),
    since: int | None = Query(None, ge=-1, le=2**62, description="Rows with env_steps > since."),
    names: str | None = Query(None, max_length=1000, description="Comma-separated metric names."),
    limit: int | None = Query(None, ge=1, le=100_000),
    control: JobControl = CONTROL,
) -> MetricsPage:
    wanted = [n.strip() for n in names.split(",") if n.strip()] if names else None
    rows = control.store.metrics(job_id, since=since, names=wanted, limit=limit)
    last = rows[-1]["env_steps"] if rows else control.store.last_step(job_id)
    return MetricsPage(job=job_id, rows=json_safe(rows), last_step=last)


SSE_RETRY_MS = 2000  # how long a browser's EventSource waits before it reconnects


@router.get("/jobs/{job_id}/events", tags=["metrics"], response_class=StreamingResponse)
async def events(
    job_id: str = PathParam(..., pattern=JOB_ID),
    since: int | None = Query(None, ge=-1, le=2**62),
    timeout: float = Query(300.0, gt=0, le=3600, description="Seconds before the stream closes."),
    last_event_id: str | None = Header(
        None, description="Sent by a reconnecting EventSource: the stream resumes after that env step."
    ),
    control: JobControl = CONTROL,
) -> StreamingResponse:
    """Server-sent events: ``metrics`` (new rows), ``state`` and ``deleted``. Every event's ``id`` is the env step
    of the last row sent, so a browser that loses the stream reconnects (after ``retry`` ms) with
    ``Last-Event-ID`` and gets exactly the rows it missed."""
    control.store.get(job_id)  # 404 before the stream starts
    if last_event_id is not None and since is None:
        try:
            since = int(last_event_id)
        except ValueError:
            raise ApiError(
                422, "Last-Event-ID", f"not an env step: {last_event_id[:40]!r}", "send the id of the last event"
            ) from None

    async def stream() -> AsyncIterator[str]:
        last, state, t_end = since, None, time.monotonic() + timeout
        yield f"retry: {SSE_RETRY_MS}\n\n"
        while time.monotonic() < t_end:
            rec = control.store.get(job_id) if control.store.exists(job_id) else None
            if rec is None:
                yield "event: deleted\ndata: {}\n\n"
                return
            rows = control.store.metrics(job_id, since=last)
            if rows:
                last = rows[-1]["env_steps"]
                yield f"id: {last}\nevent: metrics\ndata: {json.dumps(json_safe(rows))}\n\n"
            if rec.state != state:
                state = rec.state
                body = json.dumps({"state": str(state), "error": rec.error})
                yield (f"id: {last}\n" if last is not None else "") + f"event: state\ndata: {body}\n\n"
                if state in FINAL_STATES:
                    return
            await asyncio.sleep(0.5)

    return StreamingResponse(stream(), media_type="text/event-stream")


@router.get("/metrics", tags=["service"], response_class=PlainTextResponse)
def prometheus(control: JobControl = CONTROL) -> PlainTextResponse:
    from convoy.api.prometheus import exposition

    text, content_type = exposition(control.store, control)
    return PlainTextResponse(text, media_type=content_type)
