"""Helpers of the API tests: the same operation through REST and through gRPC, answers
normalised to one shape so they can be compared."""

from __future__ import annotations

import io
import json
import subprocess
import sys
import zipfile
from typing import Any

import grpc
import httpx

from renderfarm.client import Client
from renderfarm.domain.scenes.pack import pack_gltf
from renderfarm.v1 import jobs_pb2, jobs_pb2_grpc, scenes_pb2, scenes_pb2_grpc

from .conftest import CORNELL

TINY = {"width": 32, "height": 32, "tile_size": 16, "max_spp": 4, "seed": 3}


def create_token(data_dir, name: str, admin: bool = False) -> dict:
    """A new API token made with the CLI against a farm's data directory: the JSON it prints
    (id, name, admin, token)."""
    done = subprocess.run(
        [sys.executable, "-m", "renderfarm", "token", "create", name, "--json",
         "--data-dir", str(data_dir)] + (["--admin"] if admin else []),
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def cornell_glb() -> bytes:
    return pack_gltf(CORNELL)


def escaping_zip() -> bytes:
    """A bundle whose .gltf is fine but which also holds an entry climbing out with ../"""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        z.writestr("scene.gltf", CORNELL.read_bytes())
        z.writestr("../../escaped-by-test.txt", b"should never be written")
    return buf.getvalue()


def settings_message(settings: dict[str, Any]) -> jobs_pb2.RenderSettings:
    """REST-style settings as a RenderSettings message, read off the proto's own descriptor:
    an enumerated value by its name (sampler "halton" is SAMPLER_HALTON); a value the
    enumeration lacks becomes a number it lacks (99), which the server must refuse."""
    values: dict[str, Any] = {}
    for name, value in settings.items():
        field = jobs_pb2.RenderSettings.DESCRIPTOR.fields_by_name[
            "environment_sha256" if name == "environment" else name
        ]
        if field.enum_type is not None:
            known = field.enum_type.values_by_name.get(f"{name.upper()}_{str(value).upper()}")
            value = known.number if known is not None else 99
        values[field.name] = value
    return jobs_pb2.RenderSettings(**values)


def job_from_proto(job: jobs_pb2.Job) -> dict[str, Any]:
    settings = {}
    for field in job.settings.DESCRIPTOR.fields:
        name = "environment" if field.name == "environment_sha256" else field.name
        value = getattr(job.settings, field.name)
        if field.enum_type is not None:  # SAMPLER_HALTON -> "halton"
            value = field.enum_type.values_by_number[value].name[len(name) + 1 :].lower()
        settings[name] = value
    p = job.progress
    return {
        "id": job.id,
        "name": job.name,
        "state": jobs_pb2.JobState.Name(job.state)[len("JOB_STATE_") :].lower(),
        "settings": settings,
        "scene_sha256": job.scene_sha256,
        "progress": {
            "tiles_total": p.tiles_total,
            "tiles_done": p.tiles_done,
            "tiles_previewed": p.tiles_previewed,
            "mean_spp": p.mean_spp,
            "error": None if p.error < 0 else p.error,
            "eta_s": None if p.eta_s < 0 else p.eta_s,
            "samples_merged": p.samples_merged,
            "elapsed_s": p.elapsed_s,
            "frames_total": p.frames_total,
            "frames_done": p.frames_done,
        },
        "error": job.error,
        "created_unix_s": job.created_unix_s,
        "finished_unix_s": job.finished_unix_s or None,
        "owner": job.owner,
        "after": list(job.after),
        "require_tags": list(job.require_tags),
        "replica": job.replica,
    }


def comparable(job: dict[str, Any], volatile: bool = True) -> dict[str, Any]:
    """What two views of the same job must agree on (timings and live progress left out
    unless the job is finished)."""
    out = {k: v for k, v in job.items() if k not in ("stops",)}
    out["settings"] = {
        k: (float(v) if isinstance(v, float) else v) for k, v in job["settings"].items()
    }
    p = dict(job["progress"])
    p.pop("elapsed_s")
    p.pop("eta_s")
    if volatile:
        p = {"tiles_total": p["tiles_total"]}
        out.pop("state")
        out.pop("finished_unix_s")
    else:
        out["finished_unix_s"] = round(out["finished_unix_s"] or 0, 3)
    out["progress"] = p
    out["created_unix_s"] = round(out["created_unix_s"], 3)
    return out


class Error:
    """An error answer, normalised: kind (status class), field, message."""

    KINDS_HTTP = {400: "invalid", 401: "unauthenticated", 403: "forbidden", 404: "not_found",
                  409: "conflict", 413: "too_large"}  # fmt: skip
    KINDS_GRPC = {
        grpc.StatusCode.INVALID_ARGUMENT: "invalid",
        grpc.StatusCode.UNAUTHENTICATED: "unauthenticated",
        grpc.StatusCode.PERMISSION_DENIED: "forbidden",
        grpc.StatusCode.NOT_FOUND: "not_found",
        grpc.StatusCode.FAILED_PRECONDITION: "conflict",
        grpc.StatusCode.RESOURCE_EXHAUSTED: "too_large",
    }

    def __init__(self, kind: str, field: str, message: str):
        self.kind, self.field, self.message = kind, field, message

    def __repr__(self) -> str:
        return f"Error({self.kind!r}, {self.field!r}, {self.message!r})"

    @classmethod
    def from_http(cls, r: httpx.Response) -> Error:
        body = r.json()
        return cls(cls.KINDS_HTTP.get(r.status_code, str(r.status_code)), body["field"],
                   body["detail"])  # fmt: skip

    @classmethod
    def from_grpc(cls, e: grpc.RpcError) -> Error:
        field = dict(e.trailing_metadata() or ()).get("renderfarm-field", "")
        return cls(cls.KINDS_GRPC.get(e.code(), str(e.code())), field, e.details())


class Apis:
    """One farm through both APIs, with an optional bearer token."""

    def __init__(self, url: str, grpc_address: str, token: str | None = None):
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.http = httpx.Client(base_url=url, headers=headers, timeout=60)
        self.client = Client(url, token=token or "", timeout=60)
        self.channel = grpc.insecure_channel(
            grpc_address, options=[("grpc.max_receive_message_length", 64 << 20)]
        )
        self.jobs = jobs_pb2_grpc.JobServiceStub(self.channel)
        self.scenes = scenes_pb2_grpc.SceneServiceStub(self.channel)
        self.metadata = (("authorization", f"Bearer {token}"),) if token else ()

    def close(self) -> None:
        self.http.close()
        self.client.close()
        self.channel.close()

    # Each operation returns its answer, or an Error.
    def rest(self, method: str, path: str, **kw) -> Any:
        r = self.http.request(method, path, **kw)
        if r.status_code >= 400:
            return Error.from_http(r)
        if r.status_code == 204:
            return None
        if r.headers.get("content-type", "").startswith("application/json"):
            return r.json()
        return r.content

    def rpc(self, method: str, request, **kw) -> Any:
        try:
            return getattr(self.jobs, method)(request, metadata=self.metadata, timeout=60, **kw)
        except grpc.RpcError as e:
            return Error.from_grpc(e)

    def scene_rpc(self, sha: str) -> Any:
        try:
            return self.scenes.GetScene(
                scenes_pb2.GetSceneRequest(sha256=sha), metadata=self.metadata, timeout=30
            )
        except grpc.RpcError as e:
            return Error.from_grpc(e)

    def watch_rpc(self, job_id: str) -> list | Error:
        try:
            stream = self.jobs.WatchJob(
                jobs_pb2.WatchJobRequest(job_id=job_id), metadata=self.metadata, timeout=300
            )
            return [job_from_proto(m.job) for m in stream]
        except grpc.RpcError as e:
            return Error.from_grpc(e)

    def submit_rest(self, data: bytes, filename: str, settings: dict, name: str) -> Any:
        import json

        return self.rest(
            "POST",
            "/api/v1/jobs",
            files={"scene": (filename, data, "application/octet-stream")},
            data={"settings": json.dumps(settings), "name": name},
        )

    def submit_rpc(self, data: bytes, filename: str, settings: dict, name: str) -> Any:
        answer = self.rpc(
            "SubmitJob",
            jobs_pb2.SubmitJobRequest(
                scene_data=data,
                scene_filename=filename,
                name=name,
                settings=settings_message(settings),
            ),
        )
        return answer if isinstance(answer, Error) else job_from_proto(answer.job)
