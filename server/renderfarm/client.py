"""Python client of the REST API; the CLI is built on it.

from renderfarm.client import Client
c = Client("http://127.0.0.1:8080")          # or $RENDERFARM_URL; token: $RENDERFARM_TOKEN
job = c.submit("examples/cornell-box.gltf", settings={"max_spp": 256})
for job in c.watch(job["id"]):                # Server-Sent Events until the job finishes
    print(job["progress"]["tiles_done"], job["state"])
open("out.png", "wb").write(c.image(job["id"], "png"))

Errors the server answers with raise ApiError (status, message, field). An https URL is checked
against the system's certificates, or against RENDERFARM_CA_FILE / ca_file when given.

A 503 or 429 that carries Retry-After (the database is away, the server is busy, a server of
several is restarting: nothing was done) is sent again after the time it names, up to
RETRY_ATTEMPTS times within RETRY_BUDGET_S in all; then ApiError.
"""

from __future__ import annotations

import json
import os
import ssl
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any
from urllib.parse import quote

import httpx

from .domain.scenes.pack import pack_gltf

FINISHED = ("completed", "failed", "cancelled")


class ApiError(RuntimeError):
    """The server refused a request; `status` is the HTTP status, `field` what was wrong."""

    def __init__(self, status: int, message: str, field: str = ""):
        super().__init__(f"{message} (HTTP {status})")
        self.status = status
        self.message = message
        self.field = field


def _is_sha256(value: str) -> bool:
    return len(value) == 64 and all(c in "0123456789abcdef" for c in value.lower())


BUNDLE_SUFFIXES = (".zip", ".tar", ".tar.gz", ".tgz")
# USD layers and packages go as they are: the server converts them (infra/usd_import.py).
USD_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")
DEFAULT_TIMEOUT_S = 60.0


def _timeout_s() -> float:
    """$RENDERFARM_TIMEOUT_S, or 60: seconds a request may take to connect, send or answer."""
    text = os.environ.get("RENDERFARM_TIMEOUT_S", "").strip()
    if not text:
        return DEFAULT_TIMEOUT_S
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not 0 < value < float("inf"):
        raise ValueError(f"RENDERFARM_TIMEOUT_S must be a positive number of seconds, not {text!r}")
    return value


RETRY_ATTEMPTS = 8
RETRY_BUDGET_S = 60.0
_RETRY_STATUSES = (429, 503)


def _retry_after_s(response: httpx.Response) -> float | None:
    """The delay a 503/429 asks for (Retry-After in seconds; an HTTP date is not sent by
    this server), None when the response asks for no retry."""
    if response.status_code not in _RETRY_STATUSES:
        return None
    try:
        value = float(response.headers.get("retry-after", ""))
    except ValueError:
        return None
    return value if 0 <= value < float("inf") else None


class RetryAfterTransport(httpx.BaseTransport):
    """Sends a request again when the server answers 503/429 with Retry-After, after the delay
    it asks for (at least 0.1 s, at most what is left of the budget): the server documents that
    nothing was done for such an answer, so any method may be sent again. Bounded by
    `attempts` sends and `budget_s` seconds of waiting; the last answer is returned as it is."""

    def __init__(
        self,
        inner: httpx.BaseTransport,
        attempts: int = RETRY_ATTEMPTS,
        budget_s: float = RETRY_BUDGET_S,
        sleep: Callable[[float], None] = time.sleep,
    ):
        self.inner = inner
        self.attempts = attempts
        self.budget_s = budget_s
        self.sleep = sleep

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        waited = 0.0
        for attempt in range(1, self.attempts + 1):
            response = self.inner.handle_request(request)
            delay = _retry_after_s(response)
            if delay is None or attempt == self.attempts:
                return response
            delay = max(0.1, delay)
            if waited + delay > self.budget_s:
                return response
            response.read()
            response.close()
            self.sleep(delay)
            waited += delay
        raise AssertionError("unreachable")

    def close(self) -> None:
        self.inner.close()


class Client:
    def __init__(
        self,
        url: str | None = None,
        token: str | None = None,
        timeout: float | None = None,
        ca_file: str | None = None,
    ):
        self.url = (url or os.environ.get("RENDERFARM_URL") or "http://127.0.0.1:8080").rstrip("/")
        self.timeout = _timeout_s() if timeout is None else timeout
        token = token or os.environ.get("RENDERFARM_TOKEN")
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        ca_file = ca_file or os.environ.get("RENDERFARM_CA_FILE")
        verify = ssl.create_default_context(cafile=ca_file) if ca_file else True
        transport = RetryAfterTransport(httpx.HTTPTransport(verify=verify))
        self.http = httpx.Client(
            base_url=self.url, headers=headers, timeout=self.timeout, transport=transport
        )

    def close(self) -> None:
        self.http.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _check(self, response: httpx.Response) -> httpx.Response:
        if response.status_code >= 400:
            try:
                body = response.json()
                message, field = body.get("detail", response.text), body.get("field", "")
            except ValueError:
                message, field = response.text, ""
            raise ApiError(response.status_code, str(message), field)
        return response

    def submit(
        self,
        scene: str | os.PathLike | None = None,
        *,
        scene_sha256: str | None = None,
        settings: dict[str, Any] | None = None,
        name: str = "",
        after: list[str] | None = None,
        require_tags: list[str] | None = None,
    ) -> dict[str, Any]:
        """Submit a scene file (.glb, or .gltf packed with its files into a .glb; a USD layer,
        .usdz or .zip/.tar bundle, which the server converts or packs) or a stored scene's
        hash. `after`: ids of jobs it waits for (state waiting until all completed).
        `require_tags`: only workers announcing all these tags (--tag) render it.
        Returns the job."""
        after = list(after or [])
        tags = list(require_tags or [])
        for tag in tags:  # a form field splits on these: refuse rather than send other tags
            if not isinstance(tag, str) or "," in tag or any(c.isspace() for c in tag):
                raise ApiError(400, f"require_tags: bad tag {tag!r}", "require_tags")
        settings = dict(settings or {})
        env = settings.get("environment")
        env_file = None
        if env and not _is_sha256(str(env)):  # a file to upload with the job
            env_path = Path(env)
            env_file = (env_path.name, env_path.read_bytes(), "application/octet-stream")
            del settings["environment"]
        if scene is not None:
            path = Path(scene)
            if path.name.lower().endswith(BUNDLE_SUFFIXES + USD_SUFFIXES):  # the server unpacks
                data, upload_name = path.read_bytes(), path.name
            else:
                data = path.read_bytes() if path.suffix.lower() == ".glb" else pack_gltf(path)
                upload_name = path.stem + ".glb"
            fields = {"settings": json.dumps(settings), "name": name or path.stem}
            if after:
                fields["after"] = ",".join(after)
            if tags:
                fields["require_tags"] = ",".join(tags)
            files = {"scene": (upload_name, data, "model/gltf-binary")}
            if env_file:
                files["environment"] = env_file
            return self._check(self.http.post("/api/v1/jobs", data=fields, files=files)).json()
        if env_file:
            files = {"environment": env_file}
            fields = {"scene_sha256": scene_sha256 or "", "settings": json.dumps(settings)}
            fields["name"] = name
            if after:
                fields["after"] = ",".join(after)
            if tags:
                fields["require_tags"] = ",".join(tags)
            return self._check(self.http.post("/api/v1/jobs", data=fields, files=files)).json()
        body = {"scene_sha256": scene_sha256, "settings": settings, "name": name}
        if after:
            body["after"] = after
        if tags:
            body["require_tags"] = tags
        return self._check(self.http.post("/api/v1/jobs", json=body)).json()

    def get(self, job_id: str) -> dict[str, Any]:
        return self._check(self.http.get(f"/api/v1/jobs/{job_id}")).json()

    def list(self, state: str = "", page_size: int = 50, page_token: str = "") -> dict[str, Any]:
        params = {"page_size": page_size}
        if state:
            params["state"] = state
        if page_token:
            params["page_token"] = page_token
        return self._check(self.http.get("/api/v1/jobs", params=params)).json()

    def cancel(self, job_id: str) -> dict[str, Any]:
        return self._check(self.http.post(f"/api/v1/jobs/{job_id}/cancel")).json()

    def pause(self, job_id: str) -> dict[str, Any]:
        """Stop leasing the job's tasks (queued or running); merged batches are kept."""
        return self._check(self.http.post(f"/api/v1/jobs/{job_id}/pause")).json()

    def resume(self, job_id: str) -> dict[str, Any]:
        return self._check(self.http.post(f"/api/v1/jobs/{job_id}/resume")).json()

    def retry(self, job_id: str) -> dict[str, Any]:
        """Queue a failed job again, with what it had merged."""
        return self._check(self.http.post(f"/api/v1/jobs/{job_id}/retry")).json()

    def update(
        self, job_id: str, *, priority: int | None = None, name: str | None = None
    ) -> dict[str, Any]:
        """Change the priority and/or the name (None: unchanged)."""
        body: dict[str, Any] = {}
        if priority is not None:
            body["priority"] = priority
        if name is not None:
            body["name"] = name
        return self._check(self.http.patch(f"/api/v1/jobs/{job_id}", json=body)).json()

    def continue_job(
        self,
        job_id: str,
        *,
        max_spp: int | None = None,
        noise_threshold: float | None = None,
    ) -> dict[str, Any]:
        """Carry a completed job on to a higher max_spp and/or a lower noise_threshold."""
        settings: dict[str, Any] = {}
        if max_spp is not None:
            settings["max_spp"] = max_spp
        if noise_threshold is not None:
            settings["noise_threshold"] = noise_threshold
        body = {"settings": settings}
        return self._check(self.http.post(f"/api/v1/jobs/{job_id}/continue", json=body)).json()

    def delete(self, job_id: str) -> None:
        self._check(self.http.delete(f"/api/v1/jobs/{job_id}"))

    def events(self, job_id: str) -> list[dict[str, Any]]:
        return self._check(self.http.get(f"/api/v1/jobs/{job_id}/events")).json()

    def scene(self, sha256: str) -> dict[str, Any]:
        return self._check(self.http.get(f"/api/v1/scenes/{sha256}")).json()

    def whoami(self) -> dict[str, Any]:
        return self._check(self.http.get("/api/v1/whoami")).json()

    def watch(self, job_id: str, timeout_s: float | None = None) -> Iterator[dict[str, Any]]:
        """The job now and after every change (Server-Sent Events), until it finishes.

        The stream has no read timeout: a job may wait in the queue for any length of time, and
        the server sends a keep-alive comment at least every 15 s meanwhile (connecting and
        sending keep the client's timeout)."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        with self.http.stream(
            "GET", f"/api/v1/jobs/{job_id}/watch", timeout=httpx.Timeout(self.timeout, read=None)
        ) as response:
            if response.status_code >= 400:
                response.read()
                self._check(response)
            data: list[str] = []
            for line in response.iter_lines():
                if line.startswith("data:"):
                    data.append(line[5:].strip())
                elif not line and data:
                    job = json.loads("\n".join(data))
                    data = []
                    yield job
                    if job["state"] in FINISHED:
                        return
                if deadline is not None and time.monotonic() > deadline:
                    raise TimeoutError(f"job {job_id} still running after {timeout_s} s")

    def workers(self) -> list[dict[str, Any]]:
        return self._check(self.http.get("/api/v1/workers")).json()

    def replicas(self) -> list[dict[str, Any]]:
        """The servers of the farm (several over one database): id, addresses, heartbeat, the
        jobs each holds and its merge rate."""
        return self._check(self.http.get("/api/v1/replicas")).json()

    def drain_worker(self, worker_id: str) -> dict[str, Any]:
        """Admin: the worker finishes the tasks it holds and takes no more."""
        return self._worker_action(worker_id, "drain")

    def disable_worker(self, worker_id: str) -> dict[str, Any]:
        """Admin: the worker hands its tasks back at once and takes no more."""
        return self._worker_action(worker_id, "disable")

    def enable_worker(self, worker_id: str) -> dict[str, Any]:
        """Admin: a drained or disabled worker takes tasks again."""
        return self._worker_action(worker_id, "enable")

    def _worker_action(self, worker_id: str, action: str) -> dict[str, Any]:
        path = f"/api/v1/workers/{quote(worker_id, safe='')}/{action}"
        return self._check(self.http.post(path)).json()

    def image(
        self,
        job_id: str,
        fmt: str = "png",
        layer: str = "rgb",
        max_size: int = 0,
        compression: str = "zip",
        frame: int | None = None,
        group: str = "",
    ) -> bytes:
        """An image of the job: a PNG layer (max_size > 0: downscaled to fit) or the EXR
        (compression zip or none); of an animation, its first frame unless `frame` is given.
        group: the light group a PNG of layer light_group shows (empty: the first)."""
        params = {"layer": layer, "max_size": max_size, "compression": compression}
        if group:
            params["group"] = group
        response = self.http.get(f"{self._image_base(job_id, frame)}/image.{fmt}", params=params)
        return self._check(response).content

    @staticmethod
    def _image_base(job_id: str, frame: int | None) -> str:
        return f"/api/v1/jobs/{job_id}" + ("" if frame is None else f"/frames/{frame}")

    def frames(self, job_id: str) -> list[dict[str, Any]]:
        """Every frame of the job with its progress, in frame order: frame, state (queued,
        rendering or done), tiles_total, tiles_done, mean_spp, error, variant (a still: one,
        frame 0; a job with settings.variant "all": one per variant, frame its index and
        variant its name; variant is None for other jobs)."""
        return self._check(self.http.get(f"/api/v1/jobs/{job_id}/frames")).json()

    def frame_camera(self, job_id: str, frame: int = 0) -> dict[str, Any]:
        """The camera the frame was rendered through (camera.json; docs/usage.md, "Camera
        data"): fx, fy, cx, cy in pixels, world_to_camera and camera_to_world (4x4, row-major),
        near, far, ... A still's is frame 0."""
        url = f"/api/v1/jobs/{job_id}/frames/{frame}/camera.json"
        return self._check(self.http.get(url)).json()

    def pixel_mattes(self, job_id: str, x: int, y: int, frame: int = 0) -> dict[str, Any]:
        """What pixel (x, y) of an image's Cryptomatte holds (a job with settings.aovs naming
        cryptomatte; docs/usage.md, "Outputs"): objects, materials and assets, each a list of
        {name, id, coverage} by coverage, and the pixel's samples. A still's is frame 0."""
        url = f"/api/v1/jobs/{job_id}/frames/{frame}/mattes"
        return self._check(self.http.get(url, params={"x": x, "y": y})).json()

    def frame_image(self, job_id: str, frame: int, fmt: str = "png", **options: Any) -> bytes:
        """One frame of an animation job, or one variant (by index) of a job of every variant
        (image()'s options: layer, max_size, compression, group)."""
        return self.image(job_id, fmt, frame=frame, **options)

    def save_image(
        self,
        job_id: str,
        path: str | os.PathLike,
        fmt: str = "png",
        layer: str = "rgb",
        frame: int | None = None,
        group: str = "",
    ) -> None:
        """An image of the job (as image(), or frame_image() for a frame) streamed into a
        file, never whole in memory."""
        params = {"layer": layer} if fmt == "png" else {}
        if group:
            params["group"] = group
        self._download(f"{self._image_base(job_id, frame)}/image.{fmt}", params, path)

    def save_movie(self, job_id: str, path: str | os.PathLike, max_size: int = 1920) -> None:
        """The preview movie of an animation job's finished frames (H.264 MP4 at the job's
        fps, neither side above max_size) streamed into a file."""
        self._download(f"/api/v1/jobs/{job_id}/movie.mp4", {"max_size": max_size}, path)

    def _download(self, url: str, params: dict[str, Any], path: str | os.PathLike) -> None:
        """GET url streamed into the file at path (written only once the server answered)."""
        with self.http.stream("GET", url, params=params) as r:
            if r.status_code >= 400:
                r.read()
                self._check(r)
            with open(path, "wb") as f:
                for chunk in r.iter_bytes(1 << 20):
                    f.write(chunk)

    def ready(self) -> bool:
        try:
            return self.http.get("/readyz", timeout=2).status_code == 200
        except httpx.HTTPError:
            return False

    def wait(
        self,
        job_id: str,
        on_progress: Callable[[dict[str, Any]], None] | None = None,
        poll_s: float = 0.5,
        timeout_s: float | None = None,
    ) -> dict[str, Any]:
        """Poll until the job finishes (or timeout_s passes: TimeoutError)."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while True:
            job = self.get(job_id)
            if on_progress is not None:
                on_progress(job)
            if job["state"] in FINISHED:
                return job
            if deadline is not None and time.monotonic() > deadline:
                raise TimeoutError(f"job {job_id} still {job['state']} after {timeout_s} s")
            time.sleep(poll_s)
