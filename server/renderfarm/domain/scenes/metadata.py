"""A stored scene's own metadata for the outputs: KHR_xmp_json_ld (docs/usage.md, "Outputs").

The extension keeps XMP metadata as JSON-LD packets in the document's
`extensions.KHR_xmp_json_ld.packets`; an object that has metadata names its packet by index
(`extensions.KHR_xmp_json_ld.packet`). The asset's packet (`asset.extensions...`) is the
scene's: its title, creator, licence and rights, which a render of the scene carries on in its
EXR header. Only the JSON is read: a GLB's JSON chunk, without its binary data.
"""

from __future__ import annotations

import json
from typing import Any

from ...errors import SceneError
from .glb import CHUNK_HEADER, GLB_HEADER, parse_json

EXTENSION = "KHR_xmp_json_ld"
GLB_MAGIC = b"glTF"
# A GLB's JSON chunk starts after its 12-byte header and the chunk's 8-byte header.
JSON_CHUNK_OFFSET = GLB_HEADER.size + CHUNK_HEADER.size


def json_chunk_length(head: bytes) -> int | None:
    """The length of a GLB's JSON chunk from its first JSON_CHUNK_OFFSET bytes; None if head
    is not a GLB's (a .gltf is JSON throughout)."""
    if len(head) < JSON_CHUNK_OFFSET or head[:4] != GLB_MAGIC:
        return None
    length, _kind = CHUNK_HEADER.unpack_from(head, GLB_HEADER.size)
    return int(length)


def asset_xmp_packet(document: dict[str, Any]) -> dict[str, Any] | None:
    """The asset's KHR_xmp_json_ld packet, or None if it has none or a malformed one (the
    metadata is informative: the scene renders without it)."""
    try:
        index = document["asset"]["extensions"][EXTENSION]["packet"]
        packets = document["extensions"][EXTENSION]["packets"]
    except (KeyError, TypeError):
        return None
    if isinstance(index, bool) or not isinstance(index, int) or not isinstance(packets, list):
        return None
    if not 0 <= index < len(packets) or not isinstance(packets[index], dict):
        return None
    return packets[index]


def xmp_attribute(raw_json: bytes) -> str | None:
    """The asset's packet of a glTF JSON document as the EXR header attribute's text (compact
    JSON, keys sorted: the header stays a function of the scene); None without one."""
    try:
        document = parse_json(raw_json, "scene")
    except SceneError:
        return None
    packet = asset_xmp_packet(document)
    if packet is None:
        return None
    return json.dumps(packet, sort_keys=True, separators=(",", ":"), ensure_ascii=False)
