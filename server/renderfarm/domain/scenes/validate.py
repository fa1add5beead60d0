"""Scene validation and packing.

Scenes are stored content-addressed (sha256 of the uploaded bytes).  The server accepts a
binary glTF (.glb) or a self-contained .gltf whose buffers and images are all embedded as
``data:`` URIs.  :func:`inspect_scene` checks an upload's container (GLB chunks, JSON, asset
version, buffers, buffer views and images: that it is self-contained) with a
:class:`SceneError` whose message is meant for the user; what the scene says (accessors,
meshes, nodes, materials, cameras, extensions) is judged by the workers' own loader
(scene_check.py) before the server stores it.

:func:`pack_gltf` turns a .gltf with external files next to it into a single GLB, which is
the form a multi-file scene should be uploaded in.
"""

from __future__ import annotations

import base64
import binascii
import hashlib
import json
import os
import posixpath
import re
import struct
import urllib.parse
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ...errors import SceneError

__all__ = [
    "DEFAULT_MAX_BYTES",
    "SceneInfo",
    "inspect_scene",
    "pack_gltf",
]

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
}
IMAGE_MAGIC = (
    (b"\x89PNG\r\n\x1a\n", "image/png"),
    (b"\xff\xd8\xff", "image/jpeg"),
    (b"\xabKTX 20\xbb\r\n\x1a\n", "image/ktx2"),
)

UPLOAD_HINT = (
    "upload the scene as a single .glb: `renderfarm submit`/`renderfarm render` and the Python "
    "client pack a .gltf and its files into one automatically, as do Blender and gltf-transform"
)


@dataclass(frozen=True)
class SceneInfo:
    sha256: str
    format: str  # "glb" or "gltf"
    size_bytes: int
    meshes: int
    nodes: int
    extensions_required: tuple[str, ...]


# --------------------------------------------------------------------------------------
# Inspection
# --------------------------------------------------------------------------------------


def inspect_scene(data: bytes, filename: str = "", max_bytes: int = DEFAULT_MAX_BYTES) -> SceneInfo:
    """Validate an uploaded scene (.glb or self-contained .gltf) and describe it.

    The format is decided by content, not by ``filename``, which is only used in messages.
    Raises :class:`SceneError` if the scene cannot be accepted.
    """
    name = filename or "scene"
    size = len(data)
    if size == 0:
        raise SceneError(f"{name} is empty")
    if size > max_bytes:
        raise SceneError(f"{name} is {_size_text(size)}, over the limit of {_size_text(max_bytes)}")

    bin_chunk: bytes | None
    if data[:4] == GLB_MAGIC:
        fmt = "glb"
        json_bytes, bin_chunk = _split_glb(data, name)
    elif _strip_json_prefix(data)[:1] == b"{":
        fmt = "gltf"
        json_bytes, bin_chunk = data, None
    else:
        raise SceneError(f"{name} is not a glTF 2.0 file: {_describe_non_gltf(data)}")

    document = _parse_json(json_bytes, name)
    _check_asset(document)
    meshes = _list(document, "meshes")
    if not meshes:
        raise SceneError("the scene has no meshes, so there is nothing to render", "scene.meshes")
    nodes = _list(document, "nodes")

    required = _list(document, "extensionsRequired")
    for i, ext in enumerate(required):
        if not isinstance(ext, str):
            raise SceneError("extension names must be strings", f"scene.extensionsRequired[{i}]")

    buffer_lengths = _check_buffers(document, fmt, bin_chunk)
    view_lengths = _check_buffer_views(document, buffer_lengths)
    # Accessors, meshes, nodes and everything else the scene says are the loader's to judge
    # (scene_check.py): here only the container, its buffers and images.
    _check_images(document, view_lengths)

    return SceneInfo(
        sha256=hashlib.sha256(data).hexdigest(),
        format=fmt,
        size_bytes=size,
        meshes=len(meshes),
        nodes=len(nodes),
        extensions_required=tuple(required),
    )


def _size_text(n: int) -> str:
    """'512 bytes' or '300000000 bytes (286.1 MiB)'."""
    if n < 1024:
        return f"{n} bytes"
    value = float(n)
    for unit in ("KiB", "MiB", "GiB", "TiB"):
        value /= 1024
        if value < 1024 or unit == "TiB":
            break
    return f"{n} bytes ({value:.1f} {unit})"


def _strip_json_prefix(data: bytes) -> bytes:
    if data.startswith(b"\xef\xbb\xbf"):
        data = data[3:]
    return data[:64].lstrip(b" \t\r\n")


def _describe_non_gltf(data: bytes) -> str:
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


def _split_glb(data: bytes, name: str) -> tuple[bytes, bytes | None]:
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


def _parse_json(raw: bytes, name: str) -> dict[str, Any]:
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


def _check_asset(document: dict[str, Any]) -> None:
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


def _list(document: dict[str, Any], key: str) -> list[Any]:
    value = document.get(key, [])
    if not isinstance(value, list):
        raise SceneError(f"'{key}' must be an array", f"scene.{key}")
    return value


def _object(value: Any, field: str) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise SceneError(f"{field.removeprefix('scene.')} must be an object", field)
    return value


def _int(
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


def _index(obj: dict[str, Any], key: str, field: str, count: int, what: str) -> int:
    value = _int(obj, key, field)
    if value >= count:
        raise SceneError(
            f"{field.removeprefix('scene.')}.{key} refers to {what} {value}, but there are "
            f"only {count}",
            f"{field}.{key}",
        )
    return value


def _data_uri_payload(uri: str, field: str) -> tuple[str, bytes]:
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


def _external_uri_error(kind: str, index: int, uri: str, field: str) -> SceneError:
    shown = uri if len(uri) <= 200 else uri[:200] + "..."
    return SceneError(
        f"{kind} {index} refers to the external file {shown!r}; a .gltf upload must be "
        f"self-contained (every buffer and image embedded as a data: URI). Please {UPLOAD_HINT}.",
        field,
    )


def _is_meshopt_target(buffer: dict[str, Any]) -> bool:
    """A buffer without data that EXT_meshopt_compression decodes into (its `fallback`)."""
    ext = buffer.get("extensions")
    meshopt = ext.get("EXT_meshopt_compression") if isinstance(ext, dict) else None
    return "uri" not in buffer and isinstance(meshopt, dict) and meshopt.get("fallback") is True


def _check_buffers(document: dict[str, Any], fmt: str, bin_chunk: bytes | None) -> list[int]:
    """Return each buffer's byteLength after checking its data is there."""
    lengths = []
    for i, buffer in enumerate(_list(document, "buffers")):
        field = f"scene.buffers[{i}]"
        buffer = _object(buffer, field)
        byte_length = _int(buffer, "byteLength", field, minimum=1)
        uri = buffer.get("uri")
        if _is_meshopt_target(buffer):
            # Filled by decoding the views that name it; the worker's loader checks its size
            # against the scene memory limit before allocating it.
            available = byte_length
            source = "meshopt decoding"
        elif uri is None:
            if fmt != "glb" or i != 0:
                raise SceneError(
                    f"buffer {i} has no uri; only buffer 0 of a .glb may omit it "
                    "(it then refers to the GLB's BIN chunk)",
                    f"{field}.uri",
                )
            if bin_chunk is None:
                raise SceneError(
                    "buffer 0 has no uri, so it refers to the GLB's BIN chunk, but the file "
                    "has no BIN chunk",
                    f"{field}.uri",
                )
            available = len(bin_chunk)
            source = "the GLB's BIN chunk"
        elif not isinstance(uri, str):
            raise SceneError(f"buffer {i} uri must be a string", f"{field}.uri")
        elif uri[:5].lower() == "data:":
            _mime, payload = _data_uri_payload(uri, f"{field}.uri")
            available = len(payload)
            source = "its data: URI"
        else:
            raise _external_uri_error("buffer", i, uri, f"{field}.uri")
        if byte_length > available:
            raise SceneError(
                f"buffer {i} byteLength is {byte_length} bytes, larger than its data "
                f"({available} bytes in {source})",
                f"{field}.byteLength",
            )
        lengths.append(byte_length)
    return lengths


def _check_buffer_views(document: dict[str, Any], buffer_lengths: list[int]) -> list[int]:
    lengths = []
    for i, view in enumerate(_list(document, "bufferViews")):
        field = f"scene.bufferViews[{i}]"
        view = _object(view, field)
        buffer = _index(view, "buffer", field, len(buffer_lengths), "buffer")
        offset = _int(view, "byteOffset", field, default=0)
        length = _int(view, "byteLength", field, minimum=1)
        if offset + length > buffer_lengths[buffer]:
            raise SceneError(
                f"bufferView {i} (bytes {offset}..{offset + length}) points past the end of "
                f"buffer {buffer} ({buffer_lengths[buffer]} bytes)",
                field,
            )
        if "byteStride" in view:
            stride = _int(view, "byteStride", field, minimum=4)
            if stride > 252 or stride % 4:
                raise SceneError(
                    f"bufferView {i} byteStride {stride} must be a multiple of 4 between 4 and 252",
                    f"{field}.byteStride",
                )
        lengths.append(length)
    return lengths


def _check_images(document: dict[str, Any], view_lengths: list[int]) -> None:
    for i, image in enumerate(_list(document, "images")):
        field = f"scene.images[{i}]"
        image = _object(image, field)
        uri = image.get("uri")
        if uri is not None:
            if not isinstance(uri, str):
                raise SceneError(f"image {i} uri must be a string", f"{field}.uri")
            if uri[:5].lower() != "data:":
                raise _external_uri_error("image", i, uri, f"{field}.uri")
            _data_uri_payload(uri, f"{field}.uri")
        elif "bufferView" in image:
            _index(image, "bufferView", field, len(view_lengths), "bufferView")
            if not isinstance(image.get("mimeType"), str):
                raise SceneError(
                    f"image {i} is stored in a bufferView but has no mimeType",
                    f"{field}.mimeType",
                )
        else:
            raise SceneError(f"image {i} has neither a uri nor a bufferView", field)


# --------------------------------------------------------------------------------------
# Packing
# --------------------------------------------------------------------------------------


def pack_gltf(path: str | os.PathLike[str], *, max_bytes: int = DEFAULT_MAX_BYTES) -> bytes:
    """Pack a .gltf and the files it references into one GLB and return its bytes.

    A .glb is inspected and returned unchanged.  External URIs must be relative paths
    (percent-encoded as URIs) that stay inside the .gltf's directory after resolving
    symlinks; ``data:`` URIs are decoded and packed as well.  All buffers become one BIN
    chunk (buffer 0), and images with a uri become bufferViews with a mimeType.
    """
    gltf_path = Path(os.path.abspath(path))
    name = gltf_path.name
    try:
        if gltf_path.stat().st_size > max_bytes:
            raise SceneError(f"{name} is larger than the limit of {_size_text(max_bytes)}")
        raw = gltf_path.read_bytes()
    except FileNotFoundError:
        raise SceneError(f"{name} does not exist") from None
    except OSError as exc:
        raise SceneError(f"{name} cannot be read: {exc.strerror or exc}") from None
    if raw[:4] == GLB_MAGIC:
        inspect_scene(raw, name, max_bytes)
        return raw
    if not raw:
        raise SceneError(f"{name} is empty")
    if _strip_json_prefix(raw)[:1] != b"{":
        raise SceneError(f"{name} is not a glTF 2.0 file: {_describe_non_gltf(raw)}")
    base_dir = gltf_path.parent
    root = base_dir.resolve()

    def read(uri: str, field: str, what: str) -> tuple[str, bytes]:
        return _read_uri(uri, base_dir, root, field, what)

    return _pack_document(raw, name, read, max_bytes)


def pack_gltf_files(
    files: dict[str, bytes], gltf_path: str, *, max_bytes: int = DEFAULT_MAX_BYTES
) -> bytes:
    """Pack the .gltf at `gltf_path` of an in-memory file map (POSIX relative paths, as from
    an extracted bundle) and the files it references into one GLB.

    A uri resolves relative to the .gltf's directory within the map and must name a file of the
    map; one that climbs out of the map (``..`` past its root) or is absolute is refused.
    """
    name = posixpath.basename(gltf_path)
    raw = files[gltf_path]
    base_dir = posixpath.dirname(gltf_path)

    def read(uri: str, field: str, what: str) -> tuple[str, bytes]:
        if uri[:5].lower() == "data:":
            return _data_uri_payload(uri, field)
        relative = _relative_uri_path(uri, field, what, "in the bundle")
        if "\0" in relative or relative.startswith(("/", "\\")) or ":" in relative[:3]:
            raise SceneError(
                f"{what} refers to {_shown(uri)}; only paths relative to the .gltf are allowed",
                field,
            )
        joined = posixpath.normpath(posixpath.join(base_dir, relative.replace("\\", "/")))
        if joined == ".." or joined.startswith("../"):
            raise SceneError(f"{what} refers to {_shown(uri)}, which is outside the bundle", field)
        if joined not in files:
            raise SceneError(f"{what} refers to {_shown(uri)}, which is not in the bundle", field)
        return "", files[joined]

    return _pack_document(raw, name, read, max_bytes)


def _pack_document(raw: bytes, name: str, read, max_bytes: int) -> bytes:
    """The GLB of the .gltf text `raw`, with every uri fetched by read(uri, field, what)."""
    if not raw:
        raise SceneError(f"{name} is empty")
    if _strip_json_prefix(raw)[:1] != b"{":
        raise SceneError(f"{name} is not a glTF 2.0 file: {_describe_non_gltf(raw)}")
    document = _parse_json(raw, name)
    _check_asset(document)
    blob = bytearray()

    def append(data: bytes) -> int:
        while len(blob) % 4:
            blob.append(0)
        offset = len(blob)
        blob.extend(data)
        if len(blob) > max_bytes:
            raise SceneError(
                f"{name} and its files add up to more than the limit of {_size_text(max_bytes)}"
            )
        return offset

    # Where each buffer goes: (0, its offset in the BIN chunk), or, for a buffer without data
    # that meshopt decodes into, (its index among the GLB's buffers, 0): it stays a buffer of
    # its own after the BIN chunk's buffer 0.
    placed: list[tuple[int, int]] = []
    targets = []
    for i, buffer in enumerate(_list(document, "buffers")):
        field = f"scene.buffers[{i}]"
        buffer = _object(buffer, field)
        byte_length = _int(buffer, "byteLength", field, minimum=1)
        uri = buffer.get("uri")
        if _is_meshopt_target(buffer):
            targets.append(buffer)
            placed.append((len(targets), 0))
            continue
        if not isinstance(uri, str):
            raise SceneError(
                f"buffer {i} has no uri; in a .gltf every buffer must name its data",
                f"{field}.uri",
            )
        _mime, data = read(uri, f"{field}.uri", f"buffer {i}")
        if len(data) < byte_length:
            raise SceneError(
                f"buffer {i} byteLength is {byte_length} bytes, larger than its data "
                f"({len(data)} bytes in {_shown(uri)})",
                f"{field}.byteLength",
            )
        placed.append((0, append(data[:byte_length])))

    views = _list(document, "bufferViews")
    for i, view in enumerate(views):
        field = f"scene.bufferViews[{i}]"
        view = _object(view, field)
        buffer = _index(view, "buffer", field, len(placed), "buffer")
        offset = _int(view, "byteOffset", field, default=0)
        view["buffer"], start = placed[buffer]
        view["byteOffset"] = start + offset
        ext = view.get("extensions")
        meshopt = ext.get("EXT_meshopt_compression") if isinstance(ext, dict) else None
        if isinstance(meshopt, dict):  # its compressed bytes, in a buffer moved like the others
            where = f"{field}.extensions.EXT_meshopt_compression"
            source = _index(meshopt, "buffer", where, len(placed), "buffer")
            meshopt["buffer"], start = placed[source]
            meshopt["byteOffset"] = start + _int(meshopt, "byteOffset", where, default=0)

    for i, image in enumerate(_list(document, "images")):
        field = f"scene.images[{i}]"
        image = _object(image, field)
        uri = image.get("uri")
        if uri is None:
            continue
        if not isinstance(uri, str):
            raise SceneError(f"image {i} uri must be a string", f"{field}.uri")
        data_mime, data = read(uri, f"{field}.uri", f"image {i}")
        if not data:
            raise SceneError(f"image {i} ({_shown(uri)}) is empty", f"{field}.uri")
        mime = _image_mime_type(uri, data_mime, image.get("mimeType"), data)
        if mime is None:
            raise SceneError(
                f"image {i} ({_shown(uri)}) has an unknown type; use .png, .jpg/.jpeg, "
                ".ktx2 or .webp",
                f"{field}.uri",
            )
        views.append({"buffer": 0, "byteOffset": append(data), "byteLength": len(data)})
        del image["uri"]
        image["bufferView"] = len(views) - 1
        image["mimeType"] = mime

    if views:
        document["bufferViews"] = views
    while len(blob) % 4:
        blob.append(0)
    if blob or targets:
        # Buffer 0 is the BIN chunk; a scene whose only data is decoded still has one (of
        # four zero bytes), so that its decoded buffers keep their indices.
        document["buffers"] = [{"byteLength": max(len(blob), 4)}, *targets]
        while len(blob) < 4:
            blob.append(0)
    else:
        document.pop("buffers", None)

    glb = _build_glb(document, bytes(blob))
    inspect_scene(glb, name, max_bytes)
    return glb


def _shown(uri: str) -> str:
    if uri[:5].lower() == "data:":
        return "a data: URI"
    return repr(uri if len(uri) <= 200 else uri[:200] + "...")


def _relative_uri_path(uri: str, field: str, what: str, where: str) -> str:
    """The percent-decoded path of a uri that must be a relative reference (no scheme, no
    host, not empty); `where` completes the message ("in the bundle", "next to the .gltf")."""
    parts = urllib.parse.urlsplit(uri)
    relative = urllib.parse.unquote(parts.path)
    if parts.scheme or parts.netloc:
        raise SceneError(
            f"{what} refers to {_shown(uri)}, which is not a relative path {where}", field
        )
    if not relative:
        raise SceneError(f"{what} has an empty uri", field)
    return relative


def _read_uri(uri: str, base_dir: Path, root: Path, field: str, what: str) -> tuple[str, bytes]:
    """Return (media type from a data: URI or "", bytes) for a buffer or image uri."""
    if uri[:5].lower() == "data:":
        return _data_uri_payload(uri, field)
    relative = _relative_uri_path(uri, field, what, "next to the .gltf")
    if "\0" in relative:
        raise SceneError(f"{what} refers to {_shown(uri)}, which contains a NUL character", field)
    if os.path.isabs(relative) or relative.startswith(("/", "\\")):
        raise SceneError(
            f"{what} refers to the absolute path {_shown(uri)}; only paths relative to the "
            ".gltf are allowed",
            field,
        )
    try:
        target = (base_dir / relative).resolve(strict=True)
    except FileNotFoundError:
        raise SceneError(
            f"{what} refers to {_shown(uri)}, which does not exist next to the .gltf", field
        ) from None
    except (OSError, RuntimeError) as exc:
        raise SceneError(
            f"{what} refers to {_shown(uri)}, which cannot be read: {exc}", field
        ) from None
    if not target.is_relative_to(root):
        raise SceneError(
            f"{what} refers to {_shown(uri)}, which is outside the .gltf's directory", field
        )
    if not target.is_file():
        raise SceneError(f"{what} refers to {_shown(uri)}, which is not a regular file", field)
    try:
        return "", target.read_bytes()
    except OSError as exc:
        raise SceneError(
            f"{what} refers to {_shown(uri)}, which cannot be read: {exc.strerror or exc}",
            field,
        ) from None


def _image_mime_type(uri: str, data_mime: str, declared: Any, data: bytes) -> str | None:
    if uri[:5].lower() != "data:":
        path = urllib.parse.unquote(urllib.parse.urlsplit(uri).path)
        by_extension = IMAGE_MIME_TYPES.get(os.path.splitext(path)[1].lower())
        if by_extension:
            return by_extension
    if data_mime.startswith("image/"):
        return data_mime
    if isinstance(declared, str) and declared.startswith("image/"):
        return declared
    for magic, mime in IMAGE_MAGIC:
        if data.startswith(magic):
            return mime
    if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        return "image/webp"
    return None


def _build_glb(document: dict[str, Any], blob: bytes) -> bytes:
    json_bytes = json.dumps(document, separators=(",", ":"), ensure_ascii=False).encode()
    json_bytes += b" " * (-len(json_bytes) % 4)
    blob += b"\0" * (-len(blob) % 4)
    chunks = [CHUNK_HEADER.pack(len(json_bytes), CHUNK_JSON), json_bytes]
    if blob:
        chunks += [CHUNK_HEADER.pack(len(blob), CHUNK_BIN), blob]
    body = b"".join(chunks)
    return GLB_HEADER.pack(GLB_MAGIC, GLB_VERSION, GLB_HEADER.size + len(body)) + body


# --------------------------------------------------------------------------- environment maps
_HDR_MAGICS = (b"#?RADIANCE", b"#?RGBE")
_EXR_MAGIC = b"\x76\x2f\x31\x01"


def inspect_environment(
    data: bytes, filename: str = "", max_bytes: int = 256 * 2**20
) -> tuple[str, str]:
    """Check that `data` is a Radiance .hdr or OpenEXR image; return (sha256, "hdr" | "exr").

    Only the file signature is checked here; workers decode the image with OpenImageIO and
    report a non-retryable failure if it is corrupt."""
    name = filename or "environment"
    if not data:
        raise SceneError(f"{name} is empty", "environment")
    if len(data) > max_bytes:
        raise SceneError(
            f"{name} is {len(data)} bytes, over the limit of {max_bytes}", "environment"
        )
    if data.startswith(_EXR_MAGIC):
        fmt = "exr"
    elif any(data.startswith(m) for m in _HDR_MAGICS):
        fmt = "hdr"
    else:
        raise SceneError(
            f"{name} is not an environment map: expected a Radiance .hdr or an OpenEXR .exr image",
            "environment",
        )
    return hashlib.sha256(data).hexdigest(), fmt
