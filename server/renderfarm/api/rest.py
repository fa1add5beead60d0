"""REST API /api/v1 (FastAPI; OpenAPI at /docs and /openapi.json). Mirrors gRPC JobService.

Every response is declared (pydantic models in models.py), so the OpenAPI document describes exactly
what the server sends; tests/test_openapi_fuzz.py holds the server to it. Errors are JSON
{"detail": message, "field": name-of-the-offending-field}: 400 bad input, 401 no or bad token,
403 another owner's job, 404 unknown job or scene, 409 state conflict, 413 upload too large,
429 too many requests waiting for the database, 503 database unreachable (both with
Retry-After); FastAPI's and Starlette's own answers (unknown route, wrong method, a body they
cannot parse) and unexpected failures (500) are given the same shape (error_handlers.py).
Server-Sent Events are in sse.py, the session cookie in sessions.py, the web UI in static.py.

One module although over 500 lines: one short decorated handler per endpoint (the framework's
shape, which gives the OpenAPI document its operations), sharing the caller and error helpers
above them; the logic is in app/.
"""

from __future__ import annotations

import asyncio
import json
import os
from typing import Any, Literal

from fastapi import Depends, FastAPI, Query, Request
from fastapi.responses import FileResponse, JSONResponse, Response, StreamingResponse
from fastapi_offline import FastAPIOffline
from prometheus_client import CONTENT_TYPE_LATEST

from ..app.auth import Authenticator, Caller
from ..app.jobs import FarmService
from ..domain.jobspec import check_tags, setting_docs
from ..errors import Cancelled, SettingsError, TooLarge
from ..infra.images import LAYERS
from ..infra.movie import MovieError
from . import common as apicommon
from .error_handlers import add_error_handlers
from .metrics import Metrics
from .models import (
    CONTINUE_BODY,
    SUBMIT_BODY,
    UPDATE_BODY,
    ConvergencePoint,
    Frame,
    FrameCamera,
    Job,
    JobDetail,
    JobEvent,
    JobPage,
    PixelMattes,
    ReplicaInfo,
    SceneInfo,
    SettingDoc,
    WhoAmI,
    WorkerInfo,
    error_response,
    error_responses,
)
from .sessions import SESSION_COOKIE, add_session_routes, request_token
from .sse import add_watch_route
from .static import add_dashboard


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

    add_error_handlers(app)

    add_dashboard(app)

    @app.get("/healthz", include_in_schema=False)
    async def healthz() -> dict[str, str]:
        return {"status": "ok"}

    @app.get("/readyz", include_in_schema=False)
    async def readyz() -> Response:
        if not farm.ready:
            return error_response(503, "", "starting or stopping")
        try:
            await asyncio.wait_for(farm.store.ping(), timeout=5)
        except Exception as e:  # any database failure means not ready
            return error_response(503, "database", f"database unreachable: {e}")
        return JSONResponse({"status": "ready"})

    @app.get("/metrics", include_in_schema=False)
    async def prometheus() -> Response:
        return Response(metrics.render(), media_type=CONTENT_TYPE_LATEST)

    @app.get(
        "/api/v1/settings",
        summary="Job settings with their defaults",
        response_model=list[SettingDoc],
        responses=error_responses(),
    )
    async def settings_doc(_: Caller = Auth) -> list[dict[str, Any]]:
        return setting_docs(farm.settings.limits())

    @app.get(
        "/api/v1/whoami",
        summary="The caller: owner name and admin flag",
        response_model=WhoAmI,
        responses=error_responses(),
    )
    async def whoami(who: Caller = Auth) -> dict[str, Any]:
        return {"owner": who.owner, "admin": who.admin}

    add_session_routes(app, auth)

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
        responses=error_responses(404, 413),
        openapi_extra={"requestBody": SUBMIT_BODY},
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
        responses=error_responses(),
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
        responses=error_responses(403, 404),
    )
    async def get_job(job_id: str, who: Caller = Auth) -> dict:
        view = await farm.get(apicommon.job_id(job_id), who)
        return {**view.to_json(), "stops": await farm.stops(job_id)}

    @app.get(
        "/api/v1/jobs/{job_id}/convergence",
        summary="Image relative error and mean spp against elapsed time",
        response_model=list[ConvergencePoint],
        responses=error_responses(403, 404),
    )
    async def convergence(job_id: str, who: Caller = Auth) -> list[dict]:
        return await farm.convergence(apicommon.job_id(job_id), who)

    @app.post(
        "/api/v1/jobs/{job_id}/cancel",
        summary="Cancel a job (a finished job is left as it is)",
        response_model=Job,
        responses=error_responses(403, 404),
    )
    async def cancel_job(job_id: str, who: Caller = Auth) -> dict:
        return (await farm.cancel(apicommon.job_id(job_id), who)).to_json()

    @app.post(
        "/api/v1/jobs/{job_id}/pause",
        summary="Pause a queued or running job: it leases no tasks until resumed",
        response_model=Job,
        responses=error_responses(403, 404, 409),
    )
    async def pause_job(job_id: str, who: Caller = Auth) -> dict:
        return (await farm.pause(apicommon.job_id(job_id), who)).to_json()

    @app.post(
        "/api/v1/jobs/{job_id}/resume",
        summary="Resume a paused job where it was",
        response_model=Job,
        responses=error_responses(403, 404, 409),
    )
    async def resume_job(job_id: str, who: Caller = Auth) -> dict:
        return (await farm.resume(apicommon.job_id(job_id), who)).to_json()

    @app.post(
        "/api/v1/jobs/{job_id}/retry",
        summary="Queue a failed job again, keeping every batch it merged",
        response_model=Job,
        responses=error_responses(403, 404, 409),
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
        responses=error_responses(403, 404, 409),
        openapi_extra={"requestBody": CONTINUE_BODY},
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
        responses=error_responses(403, 404),
        openapi_extra={"requestBody": UPDATE_BODY},
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
        responses=error_responses(403, 404, 409),
    )
    async def delete_job(job_id: str, who: Caller = Auth) -> Response:
        await farm.delete(apicommon.job_id(job_id), who)
        return Response(status_code=204)

    @app.get(
        "/api/v1/jobs/{job_id}/events",
        summary="The job's event log",
        response_model=list[JobEvent],
        responses=error_responses(403, 404),
    )
    async def job_events(job_id: str, who: Caller = Auth) -> list[dict]:
        return await farm.events(apicommon.job_id(job_id), who)

    add_watch_route(app, farm, Auth)

    image_responses = {
        200: {
            "content": {
                "image/png": {"schema": {"type": "string", "format": "binary"}},
                "image/x-exr": {"schema": {"type": "string", "format": "binary"}},
            }
        },
        **error_responses(403, 404),
    }
    # The layers are the channel table's (domain/channels.py): listed as the parameter's enum
    # in the OpenAPI document, whence the dashboard's layer type (web/src/pages/viewer.ts).
    layer_query = Query(
        "rgb",
        description="PNG only: the layer (docs/usage.md, Outputs)",
        json_schema_extra={"enum": list(LAYERS)},
    )
    max_size_query = Query(
        0,
        description="PNG only: downscale (box filter) until neither side exceeds this; "
        "0 = full resolution",
    )
    compression_query = Query("zip", description="EXR only: zip, or none (faster, larger)")
    group_query = Query(
        "",
        description="PNG of layer light_group only: the light group (settings.light_groups; "
        "empty: the first)",
    )

    async def image_response(
        job_id: str, fmt: str, layer: str, max_size: int, compression: str, who: Caller,
        frame: int | None, group: str = "",
    ) -> Response:  # fmt: skip
        if layer not in LAYERS:
            raise SettingsError(
                "layer", f"unknown layer {layer[:40]!r}; one of {', '.join(LAYERS)}"
            )
        try:
            file = await farm.image_file(
                apicommon.job_id(job_id),
                fmt,
                layer,
                who,
                max_size,
                compression,
                frame,
                group=group,
            )
        except Cancelled:
            return error_response(503, "", "the server is stopping")
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
        "/api/v1/jobs/{job_id}/image.{fmt}",
        summary="The image (also while rendering): image.png (one layer) or image.exr (all); "
        "of an animation, its first frame",
        response_class=Response,
        responses=image_responses,
    )
    async def image(
        job_id: str,
        fmt: Literal["png", "exr"],
        layer: str = layer_query,
        max_size: int = max_size_query,
        compression: str = compression_query,
        group: str = group_query,
        who: Caller = Auth,
    ) -> Response:
        return await image_response(job_id, fmt, layer, max_size, compression, who, None, group)

    @app.get(
        "/api/v1/jobs/{job_id}/frames",
        summary="Every frame of the job with its progress (a still has one, frame 0; a job "
        "with settings.variant all has one per variant, its index the frame, with its name)",
        response_model=list[Frame],
        responses=error_responses(403, 404),
    )
    async def frames(job_id: str, who: Caller = Auth) -> list[dict]:
        return [f.to_json() for f in await farm.frames(apicommon.job_id(job_id), who)]

    @app.get(
        "/api/v1/jobs/{job_id}/frames/{frame}/image.{fmt}",
        summary="One frame of an animation, or variant of a job of every variant (by its "
        "index; also while rendering), as image.png or image.exr",
        response_class=Response,
        responses=image_responses,
    )
    async def frame_image(
        job_id: str,
        frame: int,
        fmt: Literal["png", "exr"],
        layer: str = layer_query,
        max_size: int = max_size_query,
        compression: str = compression_query,
        group: str = group_query,
        who: Caller = Auth,
    ) -> Response:
        return await image_response(job_id, fmt, layer, max_size, compression, who, frame, group)

    @app.get(
        "/api/v1/jobs/{job_id}/frames/{frame}/camera.json",
        summary="The camera the frame was rendered through: intrinsics in pixels, world-to-camera "
        "matrix, near and far (a still's is frame 0; a job of every variant's, each variant's)",
        response_model=FrameCamera,
        responses=error_responses(403, 404),
    )
    async def frame_camera(job_id: str, frame: int, who: Caller = Auth) -> dict[str, Any]:
        return await farm.frame_camera(apicommon.job_id(job_id), frame, who)

    @app.get(
        "/api/v1/jobs/{job_id}/frames/{frame}/mattes",
        summary="What a pixel of the image's Cryptomatte holds: the names of the nodes, "
        "materials and root nodes its samples hit, with their coverage (settings.aovs naming "
        "cryptomatte; a still's image is frame 0)",
        response_model=PixelMattes,
        responses=error_responses(400, 403, 404),
    )
    async def pixel_mattes(
        job_id: str,
        frame: int,
        x: int = Query(description="pixel column, from the left"),
        y: int = Query(description="pixel row, from the top"),
        who: Caller = Auth,
    ) -> dict[str, Any]:
        return await farm.pixel_mattes(apicommon.job_id(job_id), x, y, frame, who)

    @app.get(
        "/api/v1/jobs/{job_id}/movie.mp4",
        summary="A preview movie of the animation's finished frames (H.264 MP4 at the job's fps)",
        response_class=Response,
        responses={
            200: {"content": {"video/mp4": {"schema": {"type": "string", "format": "binary"}}}},
            **error_responses(403, 404, 409),
        },
    )
    async def movie(
        job_id: str,
        max_size: int = Query(
            1920, description="downscale (box filter) until neither side exceeds this"
        ),
        who: Caller = Auth,
    ) -> Response:
        try:
            path = await farm.movie_file(apicommon.job_id(job_id), who, max_size)
        except MovieError as e:  # no ffmpeg, or it failed
            return error_response(503, "", str(e))
        except Cancelled:
            return error_response(503, "", "the server is stopping")
        return FileResponse(
            path, media_type="video/mp4", filename=f"{job_id}.mp4",
            content_disposition_type="inline", headers={"Cache-Control": "no-cache"},
        )  # fmt: skip

    @app.get(
        "/api/v1/workers",
        summary="Connected workers",
        response_model=list[WorkerInfo],
        responses=error_responses(),
    )
    async def workers(_: Caller = Auth) -> list[dict]:
        return farm.workers()

    @app.get(
        "/api/v1/replicas",
        summary="The servers of the farm (several over one database): each one's jobs and "
        "heartbeat",
        response_model=list[ReplicaInfo],
        responses=error_responses(),
    )
    async def replicas(_: Caller = Auth) -> list[dict]:
        return await farm.replicas()

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
            responses=error_responses(403, 404),
            name=f"{action}_worker",
        )(control())

    @app.get(
        "/api/v1/scenes/{sha256}",
        summary="A stored scene's metadata",
        response_model=SceneInfo,
        responses=error_responses(404),
    )
    async def scene(sha256: str, _: Caller = Auth) -> dict:
        return await farm.scene_info(apicommon.scene_sha256(sha256))

    return app


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
