"""REST API /api/v1 (FastAPI; OpenAPI at /docs and /openapi.json). Mirrors gRPC JobService.

Every response is declared (pydantic models below), so the OpenAPI document describes exactly
what the server sends; tests/test_openapi_fuzz.py holds the server to it. Errors are JSON
{"detail": message, "field": name-of-the-offending-field}: 400 bad input, 401 no or bad token,
403 another owner's job, 404 unknown job or scene, 409 state conflict, 413 upload too large,
429 too many requests waiting for the database, 503 database unreachable (both with
Retry-After); FastAPI's and Starlette's own answers (unknown route, wrong method, a body they
cannot parse) and unexpected failures (500) are given the same shape.
"""

from __future__ import annotations

import asyncio
import json
import os
import time
from pathlib import Path
from typing import Any, Literal

from fastapi import Depends, FastAPI, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, Response, StreamingResponse
from fastapi.staticfiles import StaticFiles
from fastapi_offline import FastAPIOffline
from prometheus_client import CONTENT_TYPE_LATEST
from pydantic import BaseModel, Field, create_model
from sse_starlette import EventSourceResponse, ServerSentEvent
from starlette.exceptions import HTTPException as StarletteHTTPException

from ..app.auth import Authenticator, Caller
from ..app.jobs import FarmService
from ..domain.jobspec import SETTINGS, check_tags
from ..errors import (
    AuthError,
    Cancelled,
    Conflict,
    Forbidden,
    NotFound,
    SceneError,
    SettingsError,
    TooLarge,
)
from ..infra.images import LAYERS
from ..infra.store import DatabaseUnavailable
from . import common as apicommon
from .metrics import Metrics
from .sessions import SESSION_COOKIE, request_token
from .static import index_html

# The dashboard built by `make web`: package data renderfarm/web where an installed package
# carries it (the server image copies web/dist there before installing), else web/dist of this
# checkout; webui.py's page stands in for it when neither has been built.
_PACKAGED_WEB = Path(__file__).resolve().parents[1] / "web"
WEB_DIST = (
    _PACKAGED_WEB
    if (_PACKAGED_WEB / "index.html").is_file()
    else Path(__file__).resolve().parents[3] / "web" / "dist"
)


# ------------------------------------------------------------------------------ response models
class ErrorBody(BaseModel):
    detail: str = Field(description="what is wrong, for people")
    field: str = Field("", description="the offending field, e.g. settings.max_spp; may be empty")


JobSettingsModel = create_model(
    "JobSettings",
    **{s.name: (s.kind, Field(s.default, description=s.help)) for s in SETTINGS},
)


class Progress(BaseModel):
    tiles_total: int
    tiles_done: int = Field(description="tiles that have stopped")
    tiles_previewed: int = Field(
        description="tiles with at least one merged batch (all of them: a full-frame preview)"
    )
    mean_spp: float
    error: float | None = Field(description="RMS relative error over tiles; null before a merge")
    eta_s: float | None = Field(description="seconds to completion; null when unknown")
    samples_merged: int
    elapsed_s: float


class Job(BaseModel):
    id: str
    name: str
    state: Literal["queued", "running", "completed", "failed", "cancelled", "paused", "waiting"]
    settings: JobSettingsModel  # type: ignore[valid-type]
    scene_sha256: str
    progress: Progress
    error: str = Field(description="why the job failed, when it did")
    created_unix_s: float
    finished_unix_s: float | None
    owner: str = Field(description="name of the API token that submitted it; empty without auth")
    after: list[str] = Field(description="ids of the jobs it waits for (state waiting)")
    require_tags: list[str] = Field(
        description="only workers announcing all these tags (--tag) render it"
    )


class StopRecord(BaseModel):
    tile: int
    batch: int | None
    spp: int | None
    error: float | None
    reason: str | None


class JobDetail(Job):
    stops: list[StopRecord] = Field(description="every tile stop: tile, batch, spp, error, reason")


class JobPage(BaseModel):
    jobs: list[Job]
    next_page_token: str = Field(description="pass as page_token for the next page; empty: done")


class JobEvent(BaseModel):
    id: int
    kind: str
    data: dict[str, Any]
    at: float


class ConvergencePoint(BaseModel):
    t: float
    error: float | None
    mean_spp: float


class WorkerInfo(BaseModel):
    id: str
    hostname: str
    cores: int
    version: str
    connected_unix_s: float
    last_heartbeat_unix_s: float
    tasks_in_flight: int
    tasks_done: int
    samples_per_s: float
    rays_per_s: float
    busy_threads: int
    tasks_failed: int
    recent_errors: list[str]
    tags: list[str]
    state: Literal["active", "draining", "drained", "disabled"]


class SceneInfo(BaseModel):
    sha256: str
    format: Literal["glb", "gltf", "hdr", "exr"]
    filename: str
    size_bytes: int


class SettingDoc(BaseModel):
    name: str
    type: Literal["int", "float", "str", "bool"]
    default: bool | int | float | str  # bool first: false stays false, not 0
    help: str


class WhoAmI(BaseModel):
    owner: str = Field(description="owner name of the caller's jobs; empty when auth is off")
    admin: bool


class SessionIn(BaseModel):
    token: str = Field(description="an API token, checked like `Authorization: Bearer TOKEN`")


def _errors(*codes: int) -> dict[int | str, dict[str, Any]]:
    described = {
        400: "invalid request (the field is named)",
        401: "no API token, or an unknown or revoked one",
        403: "the job belongs to another owner",
        404: "no such job or scene",
        409: "the job's state does not allow this",
        413: "upload too large",
        429: "too many requests wait for the database; retry after Retry-After seconds",
        503: "the database is unreachable or busy; retry after Retry-After seconds",
    }
    codes = (400, 401, *codes, 429, 503)
    return {c: {"model": ErrorBody, "description": described[c]} for c in codes}


def _error(status: int, field: str, message: str, headers: dict | None = None) -> JSONResponse:
    return JSONResponse(
        status_code=status, content={"detail": message, "field": field}, headers=headers
    )


_SUBMIT_BODY = {
    "required": True,
    "content": {
        "multipart/form-data": {
            "schema": {
                "type": "object",
                "properties": {
                    "scene": {
                        "type": "string",
                        "format": "binary",
                        "description": ".glb, self-contained .gltf, or a .zip/.tar(.gz) bundle "
                        "of one .gltf with its files",
                    },
                    "settings": {"type": "string", "description": "job settings, a JSON object"},
                    "name": {"type": "string"},
                    "scene_sha256": {"type": "string", "description": "a stored scene instead"},
                    "environment": {
                        "type": "string",
                        "format": "binary",
                        "description": "equirectangular .hdr/.exr environment map",
                    },
                    "after": {
                        "type": "string",
                        "description": "ids of jobs to wait for, separated by commas or spaces",
                    },
                },
                "additionalProperties": False,
            }
        },
        "application/json": {
            "schema": {
                "type": "object",
                "properties": {
                    "scene_sha256": {"type": "string"},
                    "settings": {"type": "object"},
                    "name": {"type": "string"},
                    "after": {
                        "type": "array",
                        "items": {"type": "string"},
                        "description": "ids of jobs to wait for: the job is waiting until all "
                        "have completed, and fails if one fails or is cancelled",
                    },
                },
                "required": ["scene_sha256"],
                "additionalProperties": False,
            }
        },
    },
}

_UPDATE_BODY = {
    "required": True,
    "content": {
        "application/json": {
            "schema": {
                "type": "object",
                "properties": {
                    "priority": {"type": "integer", "description": "-1000..1000, higher first"},
                    "name": {"type": "string"},
                },
                "additionalProperties": False,
            }
        }
    },
}

_CONTINUE_BODY = {
    "required": True,
    "content": {
        "application/json": {
            "schema": {
                "type": "object",
                "properties": {
                    "settings": {
                        "type": "object",
                        "properties": {
                            "max_spp": {"type": "integer"},
                            "noise_threshold": {"type": "number"},
                        },
                        "additionalProperties": False,
                    }
                },
                "additionalProperties": False,
            }
        }
    },
}


def create_app(farm: FarmService, metrics: Metrics, auth: Authenticator | None = None) -> FastAPI:
    auth = auth or Authenticator.for_settings(farm.store, farm.settings)
    # /docs (Swagger UI) and /redoc load their scripts and styles from the server itself
    # (/static-offline-docs, files shipped in the fastapi-offline wheel), not from a CDN, so that
    # they work on a network without Internet access.
    app = FastAPIOffline(
        title="renderfarm",
        version="1",
        description=(
            "Progressive Monte Carlo render farm. Submit glTF scenes, watch them converge. "
            "Send `Authorization: Bearer TOKEN` once the server has API tokens (browsers: "
            "POST /api/v1/session for a session cookie instead)."
        ),
    )

    async def caller(request: Request) -> Caller:
        # The header when there is one, else the dashboard's session cookie.
        token = request_token(
            request.headers.get("authorization"), request.cookies.get(SESSION_COOKIE)
        )
        return await auth.caller(token)

    Auth = Depends(caller)  # noqa: N806 (a dependency, read like a type)

    @app.exception_handler(AuthError)
    async def _auth_error(_: Request, e: AuthError):
        return _error(401, "authorization", e.message, {"WWW-Authenticate": "Bearer"})

    @app.exception_handler(Forbidden)
    async def _forbidden(_: Request, e: Forbidden):
        return _error(403, "job_id", e.message)

    @app.exception_handler(SettingsError)
    async def _settings_error(_: Request, e: SettingsError):
        return _error(400, e.field, e.message)

    @app.exception_handler(SceneError)
    async def _scene_error(_: Request, e: SceneError):
        return _error(400, e.field, str(e))

    @app.exception_handler(TooLarge)
    async def _too_large(_: Request, e: TooLarge):
        return _error(413, e.field, e.message)

    @app.exception_handler(Conflict)
    async def _conflict(_: Request, e: Conflict):
        return _error(409, "", e.message)

    @app.exception_handler(NotFound)
    async def _not_found(_: Request, e: NotFound):
        return _error(404, "", e.message)

    @app.exception_handler(DatabaseUnavailable)
    async def _unavailable(_: Request, e: DatabaseUnavailable):
        return _error(e.status, "database", e.message, {"Retry-After": str(e.retry_after_s)})

    @app.exception_handler(RequestValidationError)
    async def _invalid(_: Request, e: RequestValidationError):
        first = e.errors()[0] if e.errors() else {}
        loc = first.get("loc", ())
        if first.get("type") == "json_invalid":  # its loc is the character offset, not a field
            return _error(400, "body", "request body is not valid JSON")
        where = [str(p) for p in loc if p not in ("query", "path", "body")]
        name = ".".join(where) or ("body" if loc[:1] == ("body",) else "")
        return _error(400, name, f"{name or 'request'}: {first.get('msg', 'invalid')}")

    @app.exception_handler(StarletteHTTPException)
    async def _http(_: Request, e: StarletteHTTPException):
        # Raised by FastAPI and Starlette themselves: 404 for an unknown path, 405 for a wrong
        # method, and 400 for a body they could not parse (JSON nested deeper than the parser
        # goes, broken multipart).
        if e.status_code != 400:
            return _error(e.status_code, "", str(e.detail), e.headers)
        detail = str(e.detail)
        if isinstance(e.__cause__, RecursionError):
            detail = "request body is not valid JSON: nested too deeply"
        return _error(400, "body", detail, e.headers)

    @app.exception_handler(Exception)
    async def _unexpected(_: Request, e: Exception):
        # A bug, not the client's fault; Starlette re-raises it after this answer, so the
        # traceback is still logged.
        return _error(500, "", "internal server error")

    @app.get("/", response_class=HTMLResponse, include_in_schema=False)
    async def index() -> Response:
        built = WEB_DIST / "index.html"
        if built.is_file():
            return FileResponse(built, headers={"Cache-Control": "no-cache"})
        return HTMLResponse(index_html())

    app.mount("/assets", _DashboardAssets(directory=WEB_DIST / "assets"), name="dashboard-assets")

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

    @app.get(
        "/api/v1/settings",
        summary="Job settings with their defaults",
        response_model=list[SettingDoc],
        responses=_errors(),
    )
    async def settings_doc(_: Caller = Auth) -> list[dict[str, Any]]:
        return [
            {"name": s.name, "type": s.kind.__name__, "default": s.default, "help": s.help}
            for s in SETTINGS
        ]

    @app.get(
        "/api/v1/whoami",
        summary="The caller: owner name and admin flag",
        response_model=WhoAmI,
        responses=_errors(),
    )
    async def whoami(who: Caller = Auth) -> dict[str, Any]:
        return {"owner": who.owner, "admin": who.admin}

    @app.post(
        "/api/v1/session",
        summary="Sign in the dashboard: check a token and keep it in an HttpOnly session cookie",
        description=(
            f"On success sets the cookie `{SESSION_COOKIE}` (HttpOnly, SameSite=Strict, Secure "
            "over TLS), which then authorizes requests without an Authorization header."
        ),
        response_model=WhoAmI,
        responses=_errors(),
    )
    async def sign_in(body: SessionIn, request: Request) -> JSONResponse:
        token = body.token.strip()
        if not token:
            raise AuthError("an API token is required")
        who = await auth.caller(token)  # AuthError: 401, and no cookie
        response = JSONResponse({"owner": who.owner, "admin": who.admin})
        response.set_cookie(
            SESSION_COOKIE,
            token,
            httponly=True,
            samesite="strict",
            secure=request.url.scheme == "https",
            path="/",
        )
        return response

    @app.delete(
        "/api/v1/session",
        status_code=204,
        summary="Sign out the dashboard: clear the session cookie",
        response_class=Response,
    )
    async def sign_out(request: Request) -> Response:
        response = Response(status_code=204)
        response.delete_cookie(
            SESSION_COOKIE,
            path="/",
            httponly=True,
            samesite="strict",
            secure=request.url.scheme == "https",
        )
        return response

    @app.post(
        "/api/v1/jobs",
        status_code=201,
        summary="Submit a job",
        description=(
            "multipart/form-data with a file field `scene` (.glb, self-contained .gltf, or a "
            ".zip/.tar/.tar.gz bundle holding one .gltf and the files it references), an "
            "optional `settings` field holding a JSON object, an optional `name`, and an "
            "optional file field `environment` (.hdr/.exr environment map); or "
            'application/json {"scene_sha256": ..., "settings": {...}, "name": ...} to '
            "render a scene already stored."
        ),
        response_model=Job,
        responses=_errors(404, 413),
        openapi_extra={"requestBody": _SUBMIT_BODY},
    )
    async def submit(request: Request, who: Caller = Auth) -> JSONResponse:
        limit = farm.settings.max_upload_bytes
        length = request.headers.get("content-length")
        if length and length.isdigit() and int(length) > 2 * limit + 1024 * 1024:
            raise TooLarge("scene", f"request is {length} bytes, over the limit of {limit} bytes")
        ctype = request.headers.get("content-type", "")
        scene_data = None
        filename = ""
        environment_data, environment_filename = None, ""
        if ctype.startswith("multipart/form-data"):
            form = await request.form(max_part_size=limit + 1)
            unknown = set(form.keys()) - {
                "scene",
                "settings",
                "name",
                "scene_sha256",
                "environment",
                "after",
                "require_tags",
            }
            if unknown:
                raise SettingsError(
                    sorted(unknown)[0][:100], f"unknown form field {sorted(unknown)[0][:100]!r}"
                )
            upload = form.get("scene")
            raw_settings = _json_field(form.get("settings"), "settings")
            name = _text_field(form.get("name"), "name")
            sha = _text_field(form.get("scene_sha256"), "scene_sha256") or None
            after = apicommon.after_ids(_text_field(form.get("after"), "after"))
            tags = check_tags("require_tags", _text_field(form.get("require_tags"), "require_tags"))
            env_upload = form.get("environment")
            if env_upload is not None and not isinstance(env_upload, str):
                environment_data = await env_upload.read()
                environment_filename = env_upload.filename or "environment"
            if upload is not None and not isinstance(upload, str):
                scene_data = await upload.read()
                filename = upload.filename or "scene"
            elif isinstance(upload, str) and upload:
                raise SettingsError("scene", "scene must be a file upload, not a text field")
        elif ctype.startswith("application/json"):
            try:
                body = await request.json()
            except ValueError:
                raise SettingsError("body", "request body is not valid JSON") from None
            except RecursionError:
                raise SettingsError(
                    "body", "request body is not valid JSON: nested too deeply"
                ) from None
            if not isinstance(body, dict):
                raise SettingsError("body", "request body must be a JSON object")
            unknown = set(body) - {"scene_sha256", "settings", "name", "after", "require_tags"}
            if unknown:
                raise SettingsError(
                    sorted(unknown)[0][:100], f"unknown field {sorted(unknown)[0][:100]!r}"
                )
            raw_settings = body.get("settings")
            if raw_settings is not None and not isinstance(raw_settings, dict):
                raise SettingsError("settings", "settings must be a JSON object")
            name = _text_field(body.get("name"), "name")
            sha = _text_field(body.get("scene_sha256"), "scene_sha256") or None
            after = apicommon.after_ids(body.get("after"))
            tags = check_tags("require_tags", body.get("require_tags"))
        else:
            raise SettingsError(
                "content-type", "send multipart/form-data (with a scene file) or application/json"
            )
        checked = apicommon.submission(
            scene_data=scene_data,
            scene_sha256=sha,
            filename=filename,
            name=name,
            environment_data=environment_data,
            environment_filename=environment_filename,
            max_upload_bytes=limit,
        )
        view = await farm.submit(
            **checked.kwargs(),
            raw_settings=raw_settings,
            after=after,
            caller=who,
            require_tags=tags,
        )
        metrics.jobs_submitted.inc()
        return JSONResponse(view.to_json(), status_code=201)

    @app.get(
        "/api/v1/jobs",
        summary="List jobs, newest first (your own; every owner's for admins)",
        response_model=JobPage,
        responses=_errors(),
    )
    async def list_jobs(
        state: str = "", page_size: int = 50, page_token: str = "", who: Caller = Auth
    ) -> dict:
        wanted = apicommon.job_state(state)
        views, token = await farm.list(
            wanted, page_size, apicommon.page_token(page_token), caller=who
        )
        return {"jobs": [v.to_json() for v in views], "next_page_token": token}

    @app.get(
        "/api/v1/jobs/{job_id}",
        summary="Get a job",
        response_model=JobDetail,
        responses=_errors(403, 404),
    )
    async def get_job(job_id: str, who: Caller = Auth) -> dict:
        view = await farm.get(apicommon.job_id(job_id), who)
        return {**view.to_json(), "stops": await farm.stops(job_id)}

    @app.get(
        "/api/v1/jobs/{job_id}/convergence",
        summary="Image relative error and mean spp against elapsed time",
        response_model=list[ConvergencePoint],
        responses=_errors(403, 404),
    )
    async def convergence(job_id: str, who: Caller = Auth) -> list[dict]:
        return await farm.convergence(apicommon.job_id(job_id), who)

    @app.post(
        "/api/v1/jobs/{job_id}/cancel",
        summary="Cancel a job (a finished job is left as it is)",
        response_model=Job,
        responses=_errors(403, 404),
    )
    async def cancel_job(job_id: str, who: Caller = Auth) -> dict:
        return (await farm.cancel(apicommon.job_id(job_id), who)).to_json()

    @app.post(
        "/api/v1/jobs/{job_id}/pause",
        summary="Pause a queued or running job: it leases no tasks until resumed",
        response_model=Job,
        responses=_errors(403, 404, 409),
    )
    async def pause_job(job_id: str, who: Caller = Auth) -> dict:
        return (await farm.pause(apicommon.job_id(job_id), who)).to_json()

    @app.post(
        "/api/v1/jobs/{job_id}/resume",
        summary="Resume a paused job where it was",
        response_model=Job,
        responses=_errors(403, 404, 409),
    )
    async def resume_job(job_id: str, who: Caller = Auth) -> dict:
        return (await farm.resume(apicommon.job_id(job_id), who)).to_json()

    @app.post(
        "/api/v1/jobs/{job_id}/retry",
        summary="Queue a failed job again, keeping every batch it merged",
        response_model=Job,
        responses=_errors(403, 404, 409),
    )
    async def retry_job(job_id: str, who: Caller = Auth) -> dict:
        return (await farm.retry(apicommon.job_id(job_id), who)).to_json()

    @app.post(
        "/api/v1/jobs/{job_id}/continue",
        summary="Carry a completed job on to a higher max_spp or a lower noise_threshold",
        description=(
            'application/json {"settings": {"max_spp": N, "noise_threshold": X}} (either or '
            "both). The result equals, bit for bit, a job submitted with these settings from "
            "the start; any other setting is refused (400 naming it)."
        ),
        response_model=Job,
        responses=_errors(403, 404, 409),
        openapi_extra={"requestBody": _CONTINUE_BODY},
    )
    async def continue_job(job_id: str, request: Request, who: Caller = Auth) -> dict:
        body = await _json_body(request, {"settings"})
        raw = body.get("settings")
        if raw is not None and not isinstance(raw, dict):
            raise SettingsError("settings", "settings must be a JSON object")
        return (await farm.continue_(apicommon.job_id(job_id), who, raw)).to_json()

    @app.patch(
        "/api/v1/jobs/{job_id}",
        summary="Change a job's priority or name",
        description='application/json {"priority": N, "name": "..."} (either or both).',
        response_model=Job,
        responses=_errors(403, 404),
        openapi_extra={"requestBody": _UPDATE_BODY},
    )
    async def update_job(job_id: str, request: Request, who: Caller = Auth) -> dict:
        body = await _json_body(request, {"priority", "name"})
        view = await farm.update(
            apicommon.job_id(job_id),
            who,
            priority=body.get("priority"),
            name=apicommon.job_name(body.get("name")),
        )
        return view.to_json()

    @app.delete(
        "/api/v1/jobs/{job_id}",
        status_code=204,
        summary="Delete a finished job with its stored data (cancel a running one first)",
        response_class=Response,
        responses=_errors(403, 404, 409),
    )
    async def delete_job(job_id: str, who: Caller = Auth) -> Response:
        await farm.delete(apicommon.job_id(job_id), who)
        return Response(status_code=204)

    @app.get(
        "/api/v1/jobs/{job_id}/events",
        summary="The job's event log",
        response_model=list[JobEvent],
        responses=_errors(403, 404),
    )
    async def job_events(job_id: str, who: Caller = Auth) -> list[dict]:
        return await farm.events(apicommon.job_id(job_id), who)

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
            **_errors(403, 404),
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

    @app.get(
        "/api/v1/jobs/{job_id}/image.{fmt}",
        summary="The image (also while rendering): image.png (one layer) or image.exr (all)",
        response_class=Response,
        responses={
            200: {
                "content": {
                    "image/png": {"schema": {"type": "string", "format": "binary"}},
                    "image/x-exr": {"schema": {"type": "string", "format": "binary"}},
                }
            },
            **_errors(403, 404),
        },
    )
    async def image(
        job_id: str,
        fmt: Literal["png", "exr"],
        layer: str = "rgb",
        max_size: int = Query(
            0,
            description="PNG only: downscale (box filter) until neither side exceeds this; "
            "0 = full resolution",
        ),
        compression: str = Query("zip", description="EXR only: zip, or none (faster, larger)"),
        who: Caller = Auth,
    ) -> Response:
        if layer not in LAYERS:
            raise SettingsError(
                "layer", f"unknown layer {layer[:40]!r}; one of {', '.join(LAYERS)}"
            )
        try:
            file = await farm.image_file(
                apicommon.job_id(job_id), fmt, layer, who, max_size, compression
            )
        except Cancelled:
            return _error(503, "", "the server is stopping")
        size = os.fstat(file.fileno()).st_size

        async def chunks():
            # Streamed from the (unlinked) scratch file: a large EXR is never held in RAM.
            with file:
                while chunk := await asyncio.to_thread(file.read, 1 << 20):
                    yield chunk

        media = apicommon.IMAGE_MEDIA_TYPES[fmt]
        headers = {"Cache-Control": "no-store", "Content-Length": str(size)}
        return StreamingResponse(chunks(), media_type=media, headers=headers)

    @app.get(
        "/api/v1/workers",
        summary="Connected workers",
        response_model=list[WorkerInfo],
        responses=_errors(),
    )
    async def workers(_: Caller = Auth) -> list[dict]:
        return farm.workers()

    for action, mode, summary in (
        ("drain", "draining", "Drain a worker (admin): it finishes its tasks and takes no more"),
        ("disable", "disabled", "Disable a worker (admin): its tasks are handed back at once"),
        ("enable", "active", "Enable a drained or disabled worker again (admin)"),
    ):

        def control(mode: str = mode):
            async def set_mode(worker_id: str, who: Caller = Auth) -> dict:
                return await farm.set_worker_mode(worker_id, mode, who)

            return set_mode

        app.post(
            f"/api/v1/workers/{{worker_id}}/{action}",
            summary=summary,
            response_model=WorkerInfo,
            responses=_errors(403, 404),
            name=f"{action}_worker",
        )(control())

    @app.get(
        "/api/v1/scenes/{sha256}",
        summary="A stored scene's metadata",
        response_model=SceneInfo,
        responses=_errors(404),
    )
    async def scene(sha256: str, _: Caller = Auth) -> dict:
        return await farm.scene_info(apicommon.scene_sha256(sha256))

    return app


class _DashboardAssets(StaticFiles):
    """web/dist/assets, or 404 for everything under /assets while the dashboard is not built
    (StaticFiles itself fails with a 500 then); checked per request, so `make web` on a running
    server is picked up."""

    def __init__(self, directory: Path):
        super().__init__(directory=directory, check_dir=False)

    async def check_config(self) -> None:
        if not Path(str(self.directory)).is_dir():
            raise StarletteHTTPException(404, "the dashboard is not built (make web)")
        await super().check_config()


async def _json_body(request: Request, known: set[str]) -> dict[str, Any]:
    """A JSON object body with only the `known` fields (an empty body is an empty object)."""
    raw = await request.body()
    if not raw.strip():
        return {}
    try:
        body = json.loads(raw)
    except ValueError:
        raise SettingsError("body", "request body is not valid JSON") from None
    except RecursionError:
        raise SettingsError("body", "request body is not valid JSON: nested too deeply") from None
    if not isinstance(body, dict):
        raise SettingsError("body", "request body must be a JSON object")
    unknown = sorted(set(body) - known)
    if unknown:
        raise SettingsError(unknown[0][:100], f"unknown field {unknown[0][:100]!r}")
    return body


def _text_field(value: Any, field: str) -> str:
    if value is None:
        return ""
    if not isinstance(value, str):
        raise SettingsError(field, f"{field} must be text")
    return value


def _json_field(value: Any, field: str) -> dict | None:
    if value is None or value == "":
        return None
    if not isinstance(value, str):
        raise SettingsError(field, f"{field} must be a JSON object in a text field")
    try:
        parsed = json.loads(value)
    except ValueError:
        raise SettingsError(field, f"{field} is not valid JSON") from None
    except RecursionError:
        raise SettingsError(field, f"{field} is not valid JSON: nested too deeply") from None
    if not isinstance(parsed, dict):
        raise SettingsError(field, f"{field} must be a JSON object")
    return parsed
