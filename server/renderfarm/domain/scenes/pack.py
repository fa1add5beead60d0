"""Packing a .gltf and the files it references into one GLB: from a directory on the
client's disk (pack_gltf: the one reading of files in domain, the user's own input) or from
an in-memory file map (pack_gltf_files: an extracted bundle, bundles.py).
"""

from __future__ import annotations

import os
import posixpath
import urllib.parse
from pathlib import Path
from typing import Any

from ...errors import SceneError
from .glb import (
    DEFAULT_MAX_BYTES,
    GLB_MAGIC,
    IMAGE_MAGIC,
    IMAGE_MIME_TYPES,
    build_glb,
    check_asset,
    data_uri_payload,
    describe_non_gltf,
    is_meshopt_target,
    json_index,
    json_int,
    json_list,
    json_object,
    parse_json,
    size_text,
    strip_json_prefix,
)
from .validate import inspect_scene


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
            raise SceneError(f"{name} is larger than the limit of {size_text(max_bytes)}")
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
    if strip_json_prefix(raw)[:1] != b"{":
        raise SceneError(f"{name} is not a glTF 2.0 file: {describe_non_gltf(raw)}")
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
            return data_uri_payload(uri, field)
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
    if strip_json_prefix(raw)[:1] != b"{":
        raise SceneError(f"{name} is not a glTF 2.0 file: {describe_non_gltf(raw)}")
    document = parse_json(raw, name)
    check_asset(document)
    blob = bytearray()

    def append(data: bytes) -> int:
        while len(blob) % 4:
            blob.append(0)
        offset = len(blob)
        blob.extend(data)
        if len(blob) > max_bytes:
            raise SceneError(
                f"{name} and its files add up to more than the limit of {size_text(max_bytes)}"
            )
        return offset

    # Where each buffer goes: (0, its offset in the BIN chunk), or, for a buffer without data
    # that meshopt decodes into, (its index among the GLB's buffers, 0): it stays a buffer of
    # its own after the BIN chunk's buffer 0.
    placed: list[tuple[int, int]] = []
    targets = []
    for i, buffer in enumerate(json_list(document, "buffers")):
        field = f"scene.buffers[{i}]"
        buffer = json_object(buffer, field)
        byte_length = json_int(buffer, "byteLength", field, minimum=1)
        uri = buffer.get("uri")
        if is_meshopt_target(buffer):
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

    views = json_list(document, "bufferViews")
    for i, view in enumerate(views):
        field = f"scene.bufferViews[{i}]"
        view = json_object(view, field)
        buffer = json_index(view, "buffer", field, len(placed), "buffer")
        offset = json_int(view, "byteOffset", field, default=0)
        view["buffer"], start = placed[buffer]
        view["byteOffset"] = start + offset
        ext = view.get("extensions")
        meshopt = ext.get("EXT_meshopt_compression") if isinstance(ext, dict) else None
        if isinstance(meshopt, dict):  # its compressed bytes, in a buffer moved like the others
            where = f"{field}.extensions.EXT_meshopt_compression"
            source = json_index(meshopt, "buffer", where, len(placed), "buffer")
            meshopt["buffer"], start = placed[source]
            meshopt["byteOffset"] = start + json_int(meshopt, "byteOffset", where, default=0)

    for i, image in enumerate(json_list(document, "images")):
        field = f"scene.images[{i}]"
        image = json_object(image, field)
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
                ".webp, .avif or .ktx2",
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

    glb = build_glb(document, bytes(blob))
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
        return data_uri_payload(uri, field)
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
    if data[4:8] == b"ftyp" and data[8:12] in (b"avif", b"avis"):
        return "image/avif"
    return None
