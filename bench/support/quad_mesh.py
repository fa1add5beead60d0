"""glTF 2.0 documents made of flat quads, for the benchmarks' procedural scenes.

A quad is four corners, counter-clockwise seen from its front. meshes() packs named groups of
quads (one material each) into one embedded buffer and returns the glTF fields that hold them.
"""

from __future__ import annotations

import base64
import struct


def _mesh_bytes(quads: list[tuple]) -> tuple[bytes, bytes, int, list[float], list[float]]:
    positions = [c for q in quads for c in q]
    indices = [i for k in range(len(quads)) for i in (4 * k, 4 * k + 1, 4 * k + 2,
                                                      4 * k, 4 * k + 2, 4 * k + 3)]  # fmt: skip
    pos = b"".join(struct.pack("<3f", *p) for p in positions)
    idx = b"".join(struct.pack("<I", i) for i in indices)
    lo = [min(p[a] for p in positions) for a in range(3)]
    hi = [max(p[a] for p in positions) for a in range(3)]
    return pos, idx, len(positions), lo, hi


def meshes(groups: list[tuple[str, list[tuple], int]]) -> dict:
    """{"meshes", "accessors", "bufferViews", "buffers"} for (name, quads, material) groups;
    mesh i is groups[i]."""
    buffer = b""
    views, accessors, out = [], [], []
    for name, quads, material in groups:
        pos, idx, count, lo, hi = _mesh_bytes(quads)
        for data, target in ((pos, 34962), (idx, 34963)):
            views.append({"buffer": 0, "byteOffset": len(buffer), "byteLength": len(data),
                          "target": target})  # fmt: skip
            buffer += data
        accessors.append({"bufferView": len(views) - 2, "componentType": 5126, "count": count,
                          "type": "VEC3", "min": lo, "max": hi})  # fmt: skip
        accessors.append({"bufferView": len(views) - 1, "componentType": 5125,
                          "count": len(idx) // 4, "type": "SCALAR"})  # fmt: skip
        out.append({"name": name, "primitives": [{
            "attributes": {"POSITION": len(accessors) - 2}, "indices": len(accessors) - 1,
            "material": material}]})  # fmt: skip
    uri = "data:application/octet-stream;base64," + base64.b64encode(buffer).decode()
    return {
        "meshes": out,
        "accessors": accessors,
        "bufferViews": views,
        "buffers": [{"byteLength": len(buffer), "uri": uri}],
    }


def diffuse(name: str, rgb: tuple[float, float, float], roughness: float = 1.0) -> dict:
    """A non-metallic glTF material."""
    return {
        "name": name,
        "pbrMetallicRoughness": {
            "baseColorFactor": [*rgb, 1],
            "metallicFactor": 0.0,
            "roughnessFactor": roughness,
        },
    }
