"""The farm's REST API over the Python standard library (Blender's Python has no httpx).

Nothing here imports bpy, so it can be used and tested outside Blender. Every refusal of the
server is raised as FarmError with the server's message and the field it names; a farm that
cannot be reached is a FarmError with status 0 and a sentence saying what to check.
"""

from __future__ import annotations

import json
import ssl
import urllib.error
import urllib.parse
import urllib.request
import uuid
from typing import Any

FINISHED = ("completed", "failed", "cancelled")


class FarmError(RuntimeError):
    """The farm refused a request (status = HTTP status, field = what was wrong) or could not
    be reached (status 0)."""

    def __init__(self, message: str, status: int = 0, field: str = ""):
        super().__init__(message)
        self.message = message
        self.status = status
        self.field = field

    def report(self) -> str:
        """One line for the artist: the message, then the offending field in brackets."""
        text = self.message
        if self.status:
            text = f"the farm refused (HTTP {self.status}): {text}"
        if self.field:
            text += f" [{self.field}]"
        return text


def _multipart(fields: dict[str, str], files: dict[str, tuple[str, bytes, str]]):
    """A multipart/form-data body: (content type, bytes)."""
    boundary = "renderfarm-" + uuid.uuid4().hex
    parts: list[bytes] = []
    for name, value in fields.items():
        parts.append(
            f'--{boundary}\r\nContent-Disposition: form-data; name="{name}"\r\n\r\n'.encode()
            + value.encode("utf-8")
            + b"\r\n"
        )
    for name, (filename, data, ctype) in files.items():
        safe = filename.replace('"', "_").replace("\r", "_").replace("\n", "_")
        head = (
            f'--{boundary}\r\nContent-Disposition: form-data; name="{name}"; '
            f'filename="{safe}"\r\nContent-Type: {ctype}\r\n\r\n'
        )
        parts.append(head.encode("utf-8") + data + b"\r\n")
    parts.append(f"--{boundary}--\r\n".encode())
    return f"multipart/form-data; boundary={boundary}", b"".join(parts)


class FarmClient:
    """One farm: its URL, API token (may be empty on a local farm without tokens), the CA file
    an https farm's certificate is checked against (empty: the system's CAs) and the seconds a
    request may take."""

    def __init__(self, url: str, token: str = "", ca_file: str = "", timeout_s: float = 60.0):
        url = (url or "").strip().rstrip("/")
        parsed = urllib.parse.urlsplit(url)
        if parsed.scheme not in ("http", "https") or not parsed.netloc:
            raise FarmError(
                f"the farm URL must be http://HOST:PORT or https://HOST:PORT, not {url!r}"
            )
        self.url = url
        self.token = (token or "").strip()
        self.timeout_s = timeout_s
        self.context = None
        if parsed.scheme == "https":
            try:
                self.context = ssl.create_default_context(cafile=ca_file or None)
            except (OSError, ssl.SSLError) as e:
                raise FarmError(f"cannot read the CA file {ca_file!r}: {e}") from None

    def _request(
        self,
        method: str,
        path: str,
        body: bytes | None = None,
        content_type: str = "",
        timeout_s: float | None = None,
    ) -> bytes:
        headers = {"Accept": "application/json"}
        if self.token:
            headers["Authorization"] = f"Bearer {self.token}"
        if content_type:
            headers["Content-Type"] = content_type
        request = urllib.request.Request(self.url + path, data=body, method=method, headers=headers)
        timeout = self.timeout_s if timeout_s is None else timeout_s
        try:
            with urllib.request.urlopen(request, timeout=timeout, context=self.context) as r:
                return r.read()
        except urllib.error.HTTPError as e:
            raise self._refusal(e) from None
        except urllib.error.URLError as e:
            reason = e.reason
            if isinstance(reason, ssl.SSLCertVerificationError):
                raise FarmError(
                    f"the farm's certificate is not trusted ({reason.verify_message}): set the CA "
                    "file in the add-on's preferences"
                ) from None
            if isinstance(reason, ConnectionRefusedError):
                raise FarmError(
                    f"connection refused by {self.url} (is the farm running?)"
                ) from None
            raise FarmError(f"cannot reach the farm at {self.url}: {reason}") from None
        except TimeoutError:
            raise FarmError(f"the farm at {self.url} did not answer within {timeout} s") from None
        except OSError as e:
            raise FarmError(f"connection to {self.url} failed: {e}") from None

    @staticmethod
    def _refusal(e: urllib.error.HTTPError) -> FarmError:
        raw = e.read()
        try:
            body = json.loads(raw)
            message, field = str(body.get("detail", "")), str(body.get("field", "") or "")
        except (ValueError, AttributeError):
            message, field = raw.decode("utf-8", "replace").strip()[:300], ""
        if e.code == 401:
            message = (
                message or "unauthorized"
            ) + " (set the API token in the add-on's preferences)"
        return FarmError(message or e.reason, e.code, field)

    def _json(self, method: str, path: str, **kwargs) -> Any:
        raw = self._request(method, path, **kwargs)
        try:
            return json.loads(raw)
        except ValueError:
            raise FarmError(
                f"the farm at {self.url} answered {path} with something not JSON"
            ) from None

    def settings(self) -> list[dict[str, Any]]:
        """GET /api/v1/settings: every job setting with its name, type, default and help."""
        return self._json("GET", "/api/v1/settings")

    def submit(self, scene: bytes, filename: str, settings: dict[str, Any], name: str) -> dict:
        """POST /api/v1/jobs (multipart): the .glb bytes, the settings object and the name."""
        ctype, body = _multipart(
            {"settings": json.dumps(settings), "name": name},
            {"scene": (filename, scene, "model/gltf-binary")},
        )
        return self._json("POST", "/api/v1/jobs", body=body, content_type=ctype)

    def job(self, job_id: str) -> dict[str, Any]:
        return self._json("GET", f"/api/v1/jobs/{urllib.parse.quote(job_id, safe='')}")

    def cancel(self, job_id: str) -> dict[str, Any]:
        return self._json("POST", f"/api/v1/jobs/{urllib.parse.quote(job_id, safe='')}/cancel")

    def image_exr(self, job_id: str) -> bytes:
        """GET /api/v1/jobs/{id}/image.exr: the multi-layer OpenEXR (colour and AOVs)."""
        return self._request("GET", f"/api/v1/jobs/{urllib.parse.quote(job_id, safe='')}/image.exr")

    def frames(self, job_id: str) -> list[dict[str, Any]]:
        """GET /api/v1/jobs/{id}/frames: every frame with its state (queued, rendering, done),
        in frame order."""
        return self._json("GET", f"/api/v1/jobs/{urllib.parse.quote(job_id, safe='')}/frames")

    def frame_exr(self, job_id: str, frame: int) -> bytes:
        """GET /api/v1/jobs/{id}/frames/{n}/image.exr: one frame's multi-layer OpenEXR."""
        quoted = urllib.parse.quote(job_id, safe="")
        return self._request("GET", f"/api/v1/jobs/{quoted}/frames/{int(frame)}/image.exr")
