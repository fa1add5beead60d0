"""Server-Sent Events: GET /api/v1/jobs/{job_id}/watch streams the job after every change."""

from __future__ import annotations

import asyncio
import json
import time

from fastapi import FastAPI
from sse_starlette import EventSourceResponse, ServerSentEvent

from ..app.auth import Caller
from ..app.jobs import FarmService
from . import common as apicommon
from .models import error_responses


def add_watch_route(app: FastAPI, farm: FarmService, Auth) -> None:  # noqa: N803 (a dependency)
    """The watch route; Auth is the REST app's caller dependency."""

    @app.get(
        "/api/v1/jobs/{job_id}/watch",
        summary="Server-Sent Events: the job now and after every change, until it finishes",
        description=(
            "Each event is `event: job` with the job as JSON in `data:`. Between events a "
            "comment line (`: ping ...`) is sent every RENDERFARM_SSE_PING_INTERVAL_S seconds "
            "(15 by default), so that a job waiting in the queue keeps its stream open."
        ),
        response_class=EventSourceResponse,
        responses={
            200: {"content": {"text/event-stream": {"schema": {"type": "string"}}}},
            **error_responses(403, 404),
        },
    )
    async def watch(job_id: str, who: Caller = Auth) -> EventSourceResponse:
        await farm.get(apicommon.job_id(job_id), who)  # 404/403 before the stream starts

        async def stream():
            last_sent = 0.0
            async for view in farm.watch(job_id, who):
                # At most ~10 updates a second per watcher; the final state is always sent.
                wait = 0.1 - (time.monotonic() - last_sent)
                if wait > 0 and not view.state.finished:
                    await asyncio.sleep(wait)
                    view = await farm.get(job_id, who)
                last_sent = time.monotonic()
                yield ServerSentEvent(json.dumps(view.to_json()), event="job")

        # Events are sent only on change; the library's keep-alive comments in between stop
        # clients and proxies from timing out on a job that waits queued. sep="\n" keeps the
        # framing the dashboard and the client have always read.
        return EventSourceResponse(stream(), ping=farm.settings.sse_ping_interval_s, sep="\n")
