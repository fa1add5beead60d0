"""The glTF 2.0 container: GLB chunks read and written, the JSON document parsed (with
messages meant for the user), typed access to its fields, data: URIs, image media types.
"""

from __future__ import annotations

import base64
import binascii
import json
import re
import struct
import urllib.parse
from typing import Any

from ...errors import SceneError

DEFAULT_MAX_BYTES = 256 * 2**20

GLB_MAGIC = b"glTF"

GLB_VERSION = 2

GLB_HEADER = struct.Struct("<4sII")

CHUNK_HEADER = struct.Struct("<II")

CHUNK_JSON = 0x4E4F534A  # "JSON"

CHUNK_BIN = 0x004E4942  # "BIN\0"

IMAGE_MIME_TYPES = {
    ".png": "image/png",
    ".jpg": "image/jpeg",
    ".jpeg": "image/jpeg",
    ".ktx2": "image/ktx2",
    ".webp": "image/webp",
    ".avif": "image/avif",
}

IMAGE_MAGIC = (
    (b"\x89PNG\r\n\x1a\n", "image/png"),
    (b"\xff\xd8\xff", "image/jpeg"),
    (b"\xabKTX 20\xbb\r\n\x1a\n", "image/ktx2"),
)


def size_text(n: int) -> str:
    """'512 bytes' or '300000000 bytes (286.1 MiB)'."""
    if n < 1024:
        return f"{n} bytes"
    value = float(n)
    for unit in ("KiB", "MiB", "GiB", "TiB"):
        value /= 1024
        if value < 1024 or unit == "TiB":
            break
    return f"{n} bytes ({value:.1f} {unit})"


def strip_json_prefix(data: bytes) -> bytes:
    if data.startswith(b"\xef\xbb\xbf"):
        data = data[3:]
    return data[:64].lstrip(b" \t\r\n")


def describe_non_gltf(data: bytes) -> str:
    for magic, mime in IMAGE_MAGIC:
        if data.startswith(magic):
            return f"it looks like an image ({mime}), not a scene"
    if data.startswith(b"PK\x03\x04"):
        return "it looks like a ZIP archive; bundles are not supported yet, upload a .glb"
    if data[:4].lower() == b"gltf":
        return "it starts with a damaged GLB magic (expected the bytes 'glTF')"
    text = data[:256].decode("utf-8", errors="replace")
    if _mostly_text(text):
        first = text.strip().splitlines()[0][:40] if text.strip() else ""
        return f"it is text that does not start with a JSON object ('{{'); it starts with {first!r}"
    return "it starts with neither the GLB magic 'glTF' nor a JSON object"


def _mostly_text(text: str) -> bool:
    printable = sum(ch != "\ufffd" and (ch.isprintable() or ch in "\t\r\n") for ch in text)
    return printable >= 0.95 * len(text)


def split_glb(data: bytes, name: str) -> tuple[bytes, bytes | None]:
    """Check the GLB container and return its JSON chunk and (optional) BIN chunk."""
    field = "scene"
    if len(data) < GLB_HEADER.size:
        raise SceneError(
            f"{name} is a damaged GLB: truncated, shorter than its 12-byte header", field
        )
    _magic, version, length = GLB_HEADER.unpack_from(data)
    if version != GLB_VERSION:
        raise SceneError(
            f"{name} is a GLB container version {version}; only version 2 (glTF 2.0) is supported",
            field,
        )
    if length != len(data):
        raise SceneError(
            f"{name} is a damaged GLB: its header says {length} bytes but the file has "
            f"{len(data)} bytes",
            field,
        )
    if length % 4:
        raise SceneError(f"{name} is a damaged GLB: its length is not a multiple of 4", field)

    json_chunk: bytes | None = None
    bin_chunk: bytes | None = None
    offset = GLB_HEADER.size
    index = 0
    while offset < length:
        if offset + CHUNK_HEADER.size > length:
            raise SceneError(f"{name} is a damaged GLB: chunk {index} header is truncated", field)
        chunk_length, chunk_type = CHUNK_HEADER.unpack_from(data, offset)
        start = offset + CHUNK_HEADER.size
        end = start + chunk_length
        if end > length:
            raise SceneError(
                f"{name} is a damaged GLB: chunk {index} ({chunk_length} bytes) runs past the "
                "end of the file",
                field,
            )
        if chunk_length % 4:
            raise SceneError(
                f"{name} is a damaged GLB: chunk {index} length {chunk_length} is not a "
                "multiple of 4 (chunks must be 4-byte aligned)",
                field,
            )
        if index == 0:
            if chunk_type != CHUNK_JSON:
                raise SceneError(
                    f"{name} is a damaged GLB: the first chunk must be the JSON chunk",
                    field,
                )
            if chunk_length == 0:
                raise SceneError(f"{name} is a damaged GLB: the JSON chunk is empty", field)
            json_chunk = data[start:end]
        elif chunk_type == CHUNK_JSON:
            raise SceneError(f"{name} is a damaged GLB: it has more than one JSON chunk", field)
        elif chunk_type == CHUNK_BIN:
            if index != 1:
                raise SceneError(
                    f"{name} is a damaged GLB: the BIN chunk must directly follow the JSON "
                    "chunk, and there may be only one",
                    field,
                )
            bin_chunk = data[start:end]
        # Chunks of other types are allowed by the specification and ignored.
        offset = end
        index += 1

    if json_chunk is None:
        raise SceneError(f"{name} is a damaged GLB: it has no JSON chunk", field)
    return json_chunk, bin_chunk


def _reject_constant(token: str) -> Any:
    raise ValueError(f"{token} is not allowed in JSON")


def parse_json(raw: bytes, name: str) -> dict[str, Any]:
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise SceneError(
            f"{name} is not valid glTF JSON: not UTF-8 text (byte {exc.start})"
        ) from None
    try:
        document = json.loads(text, parse_constant=_reject_constant)
    except json.JSONDecodeError as exc:
        raise SceneError(
            f"{name} is not valid glTF JSON: {exc.msg} at line {exc.lineno} column {exc.colno}"
        ) from None
    except (ValueError, RecursionError) as exc:
        raise SceneError(f"{name} is not valid glTF JSON: {exc}") from None
    if not isinstance(document, dict):
        raise SceneError(f"{name} is not valid glTF JSON: the top level must be an object")
    return document


def check_asset(document: dict[str, Any]) -> None:
    asset = document.get("asset")
    if not isinstance(asset, dict):
        raise SceneError(
            "the scene has no 'asset' object, so it is not a glTF 2.0 file", "scene.asset"
        )
    version = asset.get("version")
    if version is None:
        raise SceneError(
            'asset.version is missing; a glTF 2.0 file must declare version "2.0"',
            "scene.asset.version",
        )
    match = re.fullmatch(r"(\d+)\.(\d+)", version) if isinstance(version, str) else None
    if match is None or int(match.group(1)) != 2:
        raise SceneError(
            f"asset.version is {version!r}; only glTF 2.0 is supported", "scene.asset.version"
        )
    min_version = asset.get("minVersion")
    if min_version is not None and min_version != "2.0":
        raise SceneError(
            f"asset.minVersion is {min_version!r}; only glTF 2.0 is supported",
            "scene.asset.minVersion",
        )


def json_list(document: dict[str, Any], key: str) -> list[Any]:
    value = document.get(key, [])
    if not isinstance(value, list):
        raise SceneError(f"'{key}' must be an array", f"scene.{key}")
    return value


def json_object(value: Any, field: str) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise SceneError(f"{field.removeprefix('scene.')} must be an object", field)
    return value


def json_int(
    obj: dict[str, Any], key: str, field: str, *, default: int | None = None, minimum: int = 0
) -> int:
    value = obj.get(key, default)
    if value is None:
        raise SceneError(f"{field.removeprefix('scene.')}.{key} is missing", f"{field}.{key}")
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise SceneError(
            f"{field.removeprefix('scene.')}.{key} must be an integer >= {minimum}, not {value!r}",
            f"{field}.{key}",
        )
    return value


def json_index(obj: dict[str, Any], key: str, field: str, count: int, what: str) -> int:
    value = json_int(obj, key, field)
    if value >= count:
        raise SceneError(
            f"{field.removeprefix('scene.')}.{key} refers to {what} {value}, but there are "
            f"only {count}",
            f"{field}.{key}",
        )
    return value


def data_uri_payload(uri: str, field: str) -> tuple[str, bytes]:
    """Decode a data: URI; return (media type, bytes)."""
    header, comma, payload = uri[5:].partition(",")
    if not comma:
        raise SceneError(f"{field.removeprefix('scene.')} is a malformed data: URI", field)
    params = header.split(";")
    mime = params[0].strip().lower()
    if "base64" in (p.strip().lower() for p in params[1:]):
        try:
            raw = base64.b64decode(re.sub(r"\s+", "", payload), validate=True)
        except (binascii.Error, ValueError):
            raise SceneError(
                f"{field.removeprefix('scene.')} is a data: URI with invalid base64 content",
                field,
            ) from None
    else:
        raw = urllib.parse.unquote_to_bytes(payload)
    return mime, raw


def is_meshopt_target(buffer: dict[str, Any]) -> bool:
    """A buffer without data that EXT_meshopt_compression decodes into (its `fallback`)."""
    ext = buffer.get("extensions")
    meshopt = ext.get("EXT_meshopt_compression") if isinstance(ext, dict) else None
    return "uri" not in buffer and isinstance(meshopt, dict) and meshopt.get("fallback") is True


def build_glb(document: dict[str, Any], blob: bytes) -> bytes:
    json_bytes = json.dumps(document, separators=(",", ":"), ensure_ascii=False).encode()
    json_bytes += b" " * (-len(json_bytes) % 4)
    blob += b"\0" * (-len(blob) % 4)
    chunks = [CHUNK_HEADER.pack(len(json_bytes), CHUNK_JSON), json_bytes]
    if blob:
        chunks += [CHUNK_HEADER.pack(len(blob), CHUNK_BIN), blob]
    body = b"".join(chunks)
    return GLB_HEADER.pack(GLB_MAGIC, GLB_VERSION, GLB_HEADER.size + len(body)) + body
