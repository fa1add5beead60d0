"""REST API /api/v1 (FastAPI; OpenAPI at /docs and /openapi.json). Mirrors gRPC JobService.

Errors are JSON {"detail": message, "field": name-of-the-offending-field}: 400 bad settings or
scene, 404 unknown job or scene, 413 upload too large, 503 not ready.
"""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path
from typing import Any

import psycopg
from fastapi import FastAPI, HTTPException, Request
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, Response, StreamingResponse
from fastapi.staticfiles import StaticFiles
from prometheus_client import CONTENT_TYPE_LATEST
from psycopg_pool import PoolTimeout

from .jobspec import SETTINGS, SettingsError
from .metrics import Metrics
from .scenes import SceneError
from .service import Conflict, FarmService, NotFound, TooLarge
from .states import JobState
from .webui import index_html

# The dashboard built by `make web` (web/dist in this checkout); webui.py's page stands in for it
# when it has not been built.
WEB_DIST = Path(__file__).resolve().parents[2] / "web" / "dist"


def _error(status: int, field: str, message: str) -> JSONResponse:
    return JSONResponse(status_code=status, content={"detail": message, "field": field})


def create_app(farm: FarmService, metrics: Metrics) -> FastAPI:
    app = FastAPI(
        title="renderfarm",
        version="1",
        description="Progressive Monte Carlo render farm. Submit glTF scenes, watch them converge.",
    )

    @app.exception_handler(SettingsError)
    async def _settings_error(_: Request, e: SettingsError):
        return _error(400, e.field, e.message)

    @app.exception_handler(SceneError)
    async def _scene_error(_: Request, e: SceneError):
        return _error(400, e.field, str(e))

    @app.exception_handler(TooLarge)
    async def _too_large(_: Request, e: TooLarge):
        return _error(413, e.field, e.message)

    @app.exception_handler(psycopg.Error)
    async def _database(_: Request, e: psycopg.Error):
        return _error(503, "", f"database unavailable, try again: {type(e).__name__}")

    @app.exception_handler(PoolTimeout)
    async def _pool_timeout(_: Request, e: PoolTimeout):
        return _error(503, "", "database unavailable, try again")

    @app.exception_handler(Conflict)
    async def _conflict(_: Request, e: Conflict):
        return _error(409, "", e.message)

    @app.exception_handler(NotFound)
    async def _not_found(_: Request, e: NotFound):
        return _error(404, "", e.message)

    @app.get("/", response_class=HTMLResponse, include_in_schema=False)
    async def index() -> Response:
        built = WEB_DIST / "index.html"
        if built.is_file():
            return FileResponse(built, headers={"Cache-Control": "no-cache"})
        return HTMLResponse(index_html())

    app.mount(
        "/assets",
        StaticFiles(directory=WEB_DIST / "assets", check_dir=False),
        name="dashboard-assets",
    )

    @app.get("/healthz", include_in_schema=False)
    async def healthz() -> dict[str, str]:
        return {"status": "ok"}

    @app.get("/readyz", include_in_schema=False)
    async def readyz() -> Response:
        if not farm.ready:
            return _error(503, "", "starting or stopping")
        try:
            await asyncio.wait_for(farm.store.ping(), timeout=5)
        except Exception as e:  # any database failure means not ready
            return _error(503, "database", f"database unreachable: {e}")
        return JSONResponse({"status": "ready"})

    @app.get("/metrics", include_in_schema=False)
    async def prometheus() -> Response:
        return Response(metrics.render(), media_type=CONTENT_TYPE_LATEST)

    @app.get("/api/v1/settings", summary="Job settings with their defaults")
    async def settings_doc() -> list[dict[str, Any]]:
        return [
            {"name": s.name, "type": s.kind.__name__, "default": s.default, "help": s.help}
            for s in SETTINGS
        ]

    @app.post(
        "/api/v1/jobs",
        status_code=201,
        summary="Submit a job",
        description=(
            "multipart/form-data with a file field `scene` (.glb or self-contained .gltf), an "
            "optional `settings` field holding a JSON object, an optional `name`, and an "
            "optional file field `environment` (.hdr/.exr environment map); or "
            'application/json {"scene_sha256": ..., "settings": {...}, "name": ...} to '
            "render a scene already stored."
        ),
    )
    async def submit(request: Request) -> JSONResponse:
        limit = farm.settings.max_upload_bytes
        length = request.headers.get("content-length")
        if length and length.isdigit() and int(length) > limit + 1024 * 1024:
            raise TooLarge("scene", f"request is {length} bytes, over the limit of {limit} bytes")
        ctype = request.headers.get("content-type", "")
        scene_data = None
        filename = ""
        environment_data, environment_filename = None, ""
        if ctype.startswith("multipart/form-data"):
            form = await request.form(max_part_size=limit + 1)
            upload = form.get("scene")
            raw_settings = _json_field(form.get("settings"), "settings")
            name = str(form.get("name") or "")
            sha = str(form.get("scene_sha256") or "") or None
            env_upload = form.get("environment")
            if env_upload is not None and not isinstance(env_upload, str):
                environment_data = await env_upload.read()
                environment_filename = env_upload.filename or "environment"
            unknown = set(form.keys()) - {
                "scene",
                "settings",
                "name",
                "scene_sha256",
                "environment",
            }
            if unknown:
                raise SettingsError(
                    sorted(unknown)[0], f"unknown form field {sorted(unknown)[0]!r}"
                )
            if upload is not None and not isinstance(upload, str):
                scene_data = await upload.read()
                filename = upload.filename or "scene"
        elif ctype.startswith("application/json"):
            try:
                body = await request.json()
            except ValueError:
                raise SettingsError("body", "request body is not valid JSON") from None
            if not isinstance(body, dict):
                raise SettingsError("body", "request body must be a JSON object")
            unknown = set(body) - {"scene_sha256", "settings", "name"}
            if unknown:
                raise SettingsError(sorted(unknown)[0], f"unknown field {sorted(unknown)[0]!r}")
            raw_settings = body.get("settings")
            if raw_settings is not None and not isinstance(raw_settings, dict):
                raise SettingsError("settings", "settings must be a JSON object")
            name = str(body.get("name") or "")
            sha = str(body.get("scene_sha256") or "") or None
        else:
            raise SettingsError(
                "content-type", "send multipart/form-data (with a scene file) or application/json"
            )
        view = await farm.submit(
            scene_data=scene_data,
            scene_sha256=sha,
            filename=filename,
            name=name,
            raw_settings=raw_settings,
            environment_data=environment_data,
            environment_filename=environment_filename,
        )
        metrics.jobs_submitted.inc()
        return JSONResponse(view.to_json(), status_code=201)

    @app.get("/api/v1/jobs", summary="List jobs, newest first")
    async def list_jobs(state: str = "", page_size: int = 50, page_token: str = "") -> dict:
        wanted = None
        if state:
            try:
                wanted = JobState(state)
            except ValueError:
                states = ", ".join(s.value for s in JobState)
                raise SettingsError("state", f"unknown state {state!r}; one of {states}") from None
        views, token = await farm.list(wanted, page_size, page_token)
        return {"jobs": [v.to_json() for v in views], "next_page_token": token}

    @app.get("/api/v1/jobs/{job_id}", summary="Get a job")
    async def get_job(job_id: str) -> dict:
        view = await farm.get(job_id)
        return {**view.to_json(), "stops": await farm.stops(job_id)}

    @app.get(
        "/api/v1/jobs/{job_id}/convergence",
        summary="Image relative error and mean spp against elapsed time",
    )
    async def convergence(job_id: str) -> list[dict]:
        return await farm.convergence(job_id)

    @app.post("/api/v1/jobs/{job_id}/cancel", summary="Cancel a job")
    async def cancel_job(job_id: str) -> dict:
        return (await farm.cancel(job_id)).to_json()

    @app.delete(
        "/api/v1/jobs/{job_id}",
        status_code=204,
        summary="Delete a finished job with its stored data (cancel a running one first)",
    )
    async def delete_job(job_id: str) -> Response:
        await farm.delete(job_id)
        return Response(status_code=204)

    @app.get("/api/v1/jobs/{job_id}/events", summary="The job's event log")
    async def job_events(job_id: str) -> list[dict]:
        return await farm.events(job_id)

    @app.get(
        "/api/v1/jobs/{job_id}/watch",
        summary="Server-Sent Events: the job now and after every change, until it finishes",
    )
    async def watch(job_id: str) -> StreamingResponse:
        await farm.get(job_id)  # 404 before the stream starts

        async def stream():
            last_sent = 0.0
            async for view in farm.watch(job_id):
                # At most ~10 updates a second per watcher; the final state is always sent.
                wait = 0.1 - (time.monotonic() - last_sent)
                if wait > 0 and not view.state.finished:
                    await asyncio.sleep(wait)
                    view = await farm.get(job_id)
                last_sent = time.monotonic()
                yield f"event: job\ndata: {json.dumps(view.to_json())}\n\n"

        return StreamingResponse(stream(), media_type="text/event-stream")

    @app.get("/api/v1/jobs/{job_id}/image.{fmt}", summary="The image (also while rendering)")
    async def image(job_id: str, fmt: str, layer: str = "rgb") -> Response:
        data = await farm.image(job_id, fmt, layer)
        media = "image/png" if fmt == "png" else "image/x-exr"
        return Response(data, media_type=media, headers={"Cache-Control": "no-store"})

    @app.get("/api/v1/workers", summary="Connected workers")
    async def workers() -> list[dict]:
        return farm.workers()

    @app.get("/api/v1/scenes/{sha256}", summary="A stored scene's metadata")
    async def scene(sha256: str) -> dict:
        return await farm.scene_info(sha256)

    @app.exception_handler(HTTPException)
    async def _http(_: Request, e: HTTPException):
        return _error(e.status_code, "", str(e.detail))

    return app


def _json_field(value: Any, field: str) -> dict | None:
    if value is None or value == "":
        return None
    if not isinstance(value, str):
        raise SettingsError(field, f"{field} must be a JSON object in a text field")
    try:
        parsed = json.loads(value)
    except ValueError:
        raise SettingsError(field, f"{field} is not valid JSON") from None
    if not isinstance(parsed, dict):
        raise SettingsError(field, f"{field} must be a JSON object")
    return parsed
