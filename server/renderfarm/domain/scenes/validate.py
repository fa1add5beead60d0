"""Scene validation: what the server accepts as an upload.

Scenes are stored content-addressed (sha256 of the uploaded bytes).  The server accepts a
binary glTF (.glb) or a self-contained .gltf whose buffers and images are all embedded as
``data:`` URIs.  :func:`inspect_scene` checks an upload's container (GLB chunks, JSON, asset
version, buffers, buffer views and images: that it is self-contained) with a
:class:`SceneError` whose message is meant for the user; what the scene says (accessors,
meshes, nodes, materials, cameras, extensions) is judged by the workers' own loader
(infra/scene_check.py) before the server stores it.

pack.py turns a .gltf with external files next to it into a single GLB, which is the form a
multi-file scene should be uploaded in.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from typing import Any

from ...errors import SceneError, SettingsError
from ..frames import ALL_VARIANTS
from ..light_groups import scene_groups
from .glb import (
    DEFAULT_MAX_BYTES,
    GLB_MAGIC,
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
    split_glb,
    strip_json_prefix,
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
    animations: tuple[str, ...] = ()  # the names of its animations in order ("" when unnamed)
    # KHR_materials_variants: the names of its material variants in order
    variants: tuple[str, ...] = ()
    # Its light groups (domain/light_groups.py): group name -> node indices, the environment
    # last.
    light_groups: dict[str, list[int]] = field(default_factory=dict)


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
        raise SceneError(f"{name} is {size_text(size)}, over the limit of {size_text(max_bytes)}")

    bin_chunk: bytes | None
    if data[:4] == GLB_MAGIC:
        fmt = "glb"
        json_bytes, bin_chunk = split_glb(data, name)
    elif strip_json_prefix(data)[:1] == b"{":
        fmt = "gltf"
        json_bytes, bin_chunk = data, None
    else:
        raise SceneError(f"{name} is not a glTF 2.0 file: {describe_non_gltf(data)}")

    document = parse_json(json_bytes, name)
    check_asset(document)
    meshes = json_list(document, "meshes")
    if not meshes:
        raise SceneError("the scene has no meshes, so there is nothing to render", "scene.meshes")
    nodes = json_list(document, "nodes")

    required = json_list(document, "extensionsRequired")
    for i, ext in enumerate(required):
        if not isinstance(ext, str):
            raise SceneError("extension names must be strings", f"scene.extensionsRequired[{i}]")

    buffer_lengths = _check_buffers(document, fmt, bin_chunk)
    view_lengths = _check_buffer_views(document, buffer_lengths)
    # Accessors, meshes, nodes and everything else the scene says are the loader's to judge
    # (infra/scene_check.py): here only the container, its buffers and images.
    _check_images(document, view_lengths)

    return SceneInfo(
        sha256=hashlib.sha256(data).hexdigest(),
        format=fmt,
        size_bytes=size,
        meshes=len(meshes),
        nodes=len(nodes),
        extensions_required=tuple(required),
        animations=tuple(
            a.get("name", "") if isinstance(a, dict) and isinstance(a.get("name"), str) else ""
            for a in json_list(document, "animations")
        ),
        variants=variant_names(document),
        light_groups=scene_groups(document),
    )


def variant_names(document: dict) -> tuple[str, ...]:
    """KHR_materials_variants: the names of the document's variants, in index order."""
    ext = document.get("extensions")
    ext = ext.get("KHR_materials_variants") if isinstance(ext, dict) else None
    variants = ext.get("variants") if isinstance(ext, dict) else None
    if not isinstance(variants, list):
        return ()
    return tuple(
        v.get("name", "") if isinstance(v, dict) and isinstance(v.get("name"), str) else ""
        for v in variants
    )


def job_variants(
    text: str, names: tuple[str, ...], field: str = "settings.variant"
) -> tuple[str, ...]:
    """The variants a job renders one image each: all of the scene's, in order, for "all"
    (which wins over a variant of that name: give its index to render that one alone); () for
    a job of one variant or none, checked by resolve_variant. SettingsError naming the field
    for "all" on a scene without variants."""
    if text != ALL_VARIANTS:
        resolve_variant(text, names, field)
        return ()
    if not names:
        raise SettingsError(
            field,
            f'{field} "{ALL_VARIANTS}" renders every KHR_materials_variants variant of the '
            "scene, and it has none",
        )
    return tuple(names)


def resolve_variant(text: str, names: tuple[str, ...], field: str = "settings.variant") -> int:
    """The index of the variant a job names (an index, or a name), checked against the scene's
    variants; -1 for none (text empty). SettingsError naming the field otherwise."""
    if not text:
        return -1
    if text.isdigit() and int(text) < len(names):
        return int(text)
    if text in names:
        return names.index(text)
    known = ", ".join(f"{i} {n!r}" for i, n in enumerate(names)) or "it has none"
    raise SettingsError(
        field, f"{field}: the scene has no variant {text[:60]!r} (variants: {known})"
    )


def _external_uri_error(kind: str, index: int, uri: str, field: str) -> SceneError:
    shown = uri if len(uri) <= 200 else uri[:200] + "..."
    return SceneError(
        f"{kind} {index} refers to the external file {shown!r}; a .gltf upload must be "
        f"self-contained (every buffer and image embedded as a data: URI). Please {UPLOAD_HINT}.",
        field,
    )


def _check_buffers(document: dict[str, Any], fmt: str, bin_chunk: bytes | None) -> list[int]:
    """Return each buffer's byteLength after checking its data is there."""
    lengths = []
    for i, buffer in enumerate(json_list(document, "buffers")):
        field = f"scene.buffers[{i}]"
        buffer = json_object(buffer, field)
        byte_length = json_int(buffer, "byteLength", field, minimum=1)
        uri = buffer.get("uri")
        if is_meshopt_target(buffer):
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
            _mime, payload = data_uri_payload(uri, f"{field}.uri")
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
    for i, view in enumerate(json_list(document, "bufferViews")):
        field = f"scene.bufferViews[{i}]"
        view = json_object(view, field)
        buffer = json_index(view, "buffer", field, len(buffer_lengths), "buffer")
        offset = json_int(view, "byteOffset", field, default=0)
        length = json_int(view, "byteLength", field, minimum=1)
        if offset + length > buffer_lengths[buffer]:
            raise SceneError(
                f"bufferView {i} (bytes {offset}..{offset + length}) points past the end of "
                f"buffer {buffer} ({buffer_lengths[buffer]} bytes)",
                field,
            )
        if "byteStride" in view:
            stride = json_int(view, "byteStride", field, minimum=4)
            if stride > 252 or stride % 4:
                raise SceneError(
                    f"bufferView {i} byteStride {stride} must be a multiple of 4 between 4 and 252",
                    f"{field}.byteStride",
                )
        lengths.append(length)
    return lengths


def _check_images(document: dict[str, Any], view_lengths: list[int]) -> None:
    for i, image in enumerate(json_list(document, "images")):
        field = f"scene.images[{i}]"
        image = json_object(image, field)
        uri = image.get("uri")
        if uri is not None:
            if not isinstance(uri, str):
                raise SceneError(f"image {i} uri must be a string", f"{field}.uri")
            if uri[:5].lower() != "data:":
                raise _external_uri_error("image", i, uri, f"{field}.uri")
            data_uri_payload(uri, f"{field}.uri")
        elif "bufferView" in image:
            json_index(image, "bufferView", field, len(view_lengths), "bufferView")
            if not isinstance(image.get("mimeType"), str):
                raise SceneError(
                    f"image {i} is stored in a bufferView but has no mimeType",
                    f"{field}.mimeType",
                )
        else:
            raise SceneError(f"image {i} has neither a uri nor a bufferView", field)
