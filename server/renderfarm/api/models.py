"""The REST API's bodies as declared in its OpenAPI document: pydantic response models, the
error shape ({"detail", "field"}) and the per-route error responses, and the request bodies
written out by hand (multipart and JSON alternatives that FastAPI cannot derive)."""

from __future__ import annotations

from typing import Any, Literal

from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field, create_model

from ..domain.jobspec import SETTINGS


class ErrorBody(BaseModel):
    detail: str = Field(description="what is wrong, for people")
    field: str = Field("", description="the offending field, e.g. settings.max_spp; may be empty")


def _setting_field(s) -> tuple[type, Any]:
    """A job setting as a pydantic field: its type (an enumeration: its values, so the OpenAPI
    document and the dashboard's generated types list them), default, help and fixed range (a
    range set by the server's configuration is in /api/v1/settings)."""
    bounds: dict[str, float] = {}
    if s.minimum is not None:
        bounds["gt" if s.exclusive_minimum else "ge"] = s.minimum
    if s.maximum is not None and not s.limit:
        bounds["le"] = s.maximum
    kind = Literal[s.choices] if s.choices else s.kind
    return kind, Field(s.default, description=s.help, **bounds)


JobSettingsModel = create_model("JobSettings", **{s.name: _setting_field(s) for s in SETTINGS})


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
    frames_total: int = Field(
        1, description="images the job renders: its frames (or variants), 1 for a still"
    )
    frames_done: int = Field(0, description="frames whose every tile has stopped")


class Frame(BaseModel):
    frame: int = Field(description="the frame number (0 for a still)")
    state: Literal["queued", "rendering", "done"] = Field(
        description="queued: nothing merged yet; done: every tile has stopped"
    )
    tiles_total: int
    tiles_done: int
    mean_spp: float
    error: float | None = Field(description="RMS relative error over its tiles; null before one")
    variant: str | None = Field(
        None,
        description='settings.variant "all": the name of the variant this image renders (its '
        "index is the frame number); null for other jobs",
    )


Matrix4 = list[list[float]]


class FrameCamera(BaseModel):
    """The camera an image was rendered through (docs/usage.md, "Camera data")."""

    frame: int = Field(description="the frame number (0 for a still; a variant's index)")
    time_s: float | None = Field(
        description="the glTF time the camera is posed at, frame / fps; null for a still "
        "(the scene as stored, no animation)"
    )
    shutter_s: list[float] | None = Field(
        description="motion blur: the glTF times the shutter opens and closes (the camera data "
        "is that of time_s even when the camera moves during the shutter); null without"
    )
    projection: Literal["perspective", "orthographic"]
    width: int = Field(description="image width in pixels")
    height: int = Field(description="image height in pixels")
    fx: float = Field(
        description="perspective: focal length in pixels; orthographic: pixels per unit of "
        "camera-space x, W / (2 xmag)"
    )
    fy: float = Field(description="as fx, vertically: (H / 2) / tan(yfov / 2), or H / (2 ymag)")
    cx: float = Field(description="principal point, pixels from the left edge: W / 2")
    cy: float = Field(description="principal point, pixels from the top edge: H / 2")
    yfov: float | None = Field(description="vertical field of view, radians; null: orthographic")
    xmag: float | None = Field(description="orthographic half width; null: perspective")
    ymag: float | None = Field(description="orthographic half height; null: perspective")
    world_to_camera: Matrix4 = Field(description="4x4, row-major, column vectors: p_c = M p_w")
    camera_to_world: Matrix4 = Field(description="4x4, row-major: its inverse")
    convention: str = Field(description="the camera space and pixel convention, in words")
    near: float = Field(description="znear: nothing nearer along the view axis is seen")
    far: float | None = Field(description="zfar; null: infinite")
    node: int | None = Field(
        description="the glTF node of the camera; null: the scene has none and the renderer "
        "framed its bounds"
    )


class Matte(BaseModel):
    name: str = Field(description="the glTF node's, material's or root node's name")
    id: str = Field(description="its Cryptomatte ID: 8 hex digits of the float's bits")
    coverage: float = Field(description="the share of the pixel's samples whose first hit it is")


class PixelMattes(BaseModel):
    """What a pixel of a job's Cryptomatte holds (docs/usage.md, "Cryptomatte")."""

    x: int
    y: int
    samples: int = Field(description="samples merged into the pixel so far")
    objects: list[Matte] = Field(description="CryptoObject: glTF nodes, by coverage")
    materials: list[Matte] = Field(description="CryptoMaterial: glTF materials, by coverage")
    assets: list[Matte] = Field(description="CryptoAsset: root nodes, by coverage")


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
    replica: str = Field(
        "",
        description="the server (RENDERFARM_REPLICA_ID) that owns and renders the job now; "
        "empty when none does (a finished job)",
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


class ReplicaInfo(BaseModel):
    id: str = Field(description="the server's RENDERFARM_REPLICA_ID")
    addresses: dict[str, str] = Field(description="where it answers: http (REST) and grpc")
    started_unix_s: float | None
    heartbeat_unix_s: float = Field(description="its last heartbeat (the database's clock)")
    live: bool = Field(description="it heartbeat within twice the job lease")
    jobs_owned: int = Field(description="jobs it holds a live lease on")
    batches_merged: int = Field(description="batches it merged since it started")
    merge_rate: float | None = Field(
        description="batches merged per second between its last two heartbeats"
    )


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
    choices: list[str] = Field([], description="the values of an enumerated setting")
    minimum: float | None = Field(None, description="lowest value (exclusive_minimum: above it)")
    exclusive_minimum: bool = False
    maximum: float | None = Field(None, description="highest value (this server's limit)")
    unit: str = Field("", description="px, s, m, deg or empty")
    derived: bool = Field(
        False, description="filled in by the server (from the scene), not chosen: forms omit it"
    )


class WhoAmI(BaseModel):
    owner: str = Field(description="owner name of the caller's jobs; empty when auth is off")
    admin: bool


class SessionIn(BaseModel):
    token: str = Field(description="an API token, checked like `Authorization: Bearer TOKEN`")


def error_responses(*codes: int) -> dict[int | str, dict[str, Any]]:
    described = {
        400: "invalid request (the field is named)",
        401: "no API token, or an unknown or revoked one",
        403: "the job belongs to another owner",
        404: "no such job or scene, or a frame the job does not render",
        409: "the job's state does not allow this",
        413: "upload too large",
        429: "too many requests wait for the database; retry after Retry-After seconds",
        503: "the database is unreachable or busy (retry after Retry-After seconds), the server "
        "is stopping, or it lacks a tool the request needs (ffmpeg for movies)",
    }
    codes = (400, 401, *codes, 429, 503)
    return {c: {"model": ErrorBody, "description": described[c]} for c in codes}


def error_response(
    status: int, field: str, message: str, headers: dict | None = None
) -> JSONResponse:
    return JSONResponse(
        status_code=status, content={"detail": message, "field": field}, headers=headers
    )


SUBMIT_BODY = {
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

UPDATE_BODY = {
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

CONTINUE_BODY = {
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
