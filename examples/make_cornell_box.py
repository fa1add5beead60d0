#!/usr/bin/env python3
"""Write the classic Cornell box as glTF 2.0 (cornell-box.gltf + cornell-box.bin).

The geometry is the measured data published by the Cornell University Program of
Computer Graphics ("Cornell Box Data", https://www.graphics.cornell.edu/online/box/data.html).
The published coordinates are in millimetres; the glTF file is written in metres.

The renderer treats emission as one-sided from the front face, with the front face
given by counter-clockwise winding (geometric normal = normalize(cross(p1 - p0, p2 - p0))).
Every quad is therefore oriented here: the room (floor, ceiling, walls) faces into the
box, block faces face away from their block's centre, and the light faces down.

Usage:
    python make_cornell_box.py            # write the files next to this script, then check
    python make_cornell_box.py --check    # only re-read and verify the written files
"""

from __future__ import annotations

import argparse
import json
import math
import re
import struct
import sys
from pathlib import Path

# --------------------------------------------------------------------------------------
# Scene data, in millimetres, copied from the Cornell "Cornell Box Data" page (see above).
# Each quad lists its four corners in the published order; the winding is fixed up below.
# --------------------------------------------------------------------------------------

# fmt: off
# Room: (name, material, corners).  These face toward the centre of the box.
ROOM_QUADS = (
    ("floor", "white", ((552.8, 0.0, 0.0), (0.0, 0.0, 0.0),
                        (0.0, 0.0, 559.2), (549.6, 0.0, 559.2))),
    ("ceiling", "white", ((556.0, 548.8, 0.0), (556.0, 548.8, 559.2),
                          (0.0, 548.8, 559.2), (0.0, 548.8, 0.0))),
    ("back_wall", "white", ((549.6, 0.0, 559.2), (0.0, 0.0, 559.2),
                            (0.0, 548.8, 559.2), (556.0, 548.8, 559.2))),
    ("right_wall", "green", ((0.0, 0.0, 559.2), (0.0, 0.0, 0.0),
                             (0.0, 548.8, 0.0), (0.0, 548.8, 559.2))),
    ("left_wall", "red", ((552.8, 0.0, 0.0), (549.6, 0.0, 559.2),
                          (556.0, 548.8, 559.2), (556.0, 548.8, 0.0))),
)

# Light: published at the ceiling height (548.8 mm).  It is moved LIGHT_DROP_MM down so
# that it does not coincide with the ceiling plane.  It faces down (-y).
LIGHT_QUAD = ((343.0, 548.8, 227.0), (343.0, 548.8, 332.0),
              (213.0, 548.8, 332.0), (213.0, 548.8, 227.0))
LIGHT_DROP_MM = 0.5

# Blocks: the five visible faces of each (top, then four sides).  They face outward.
SHORT_BLOCK = (
    ((130.0, 165.0, 65.0), (82.0, 165.0, 225.0), (240.0, 165.0, 272.0), (290.0, 165.0, 114.0)),
    ((290.0, 0.0, 114.0), (290.0, 165.0, 114.0), (240.0, 165.0, 272.0), (240.0, 0.0, 272.0)),
    ((130.0, 0.0, 65.0), (130.0, 165.0, 65.0), (290.0, 165.0, 114.0), (290.0, 0.0, 114.0)),
    ((82.0, 0.0, 225.0), (82.0, 165.0, 225.0), (130.0, 165.0, 65.0), (130.0, 0.0, 65.0)),
    ((240.0, 0.0, 272.0), (240.0, 165.0, 272.0), (82.0, 165.0, 225.0), (82.0, 0.0, 225.0)),
)
TALL_BLOCK = (
    ((423.0, 330.0, 247.0), (265.0, 330.0, 296.0), (314.0, 330.0, 456.0), (472.0, 330.0, 406.0)),
    ((423.0, 0.0, 247.0), (423.0, 330.0, 247.0), (472.0, 330.0, 406.0), (472.0, 0.0, 406.0)),
    ((472.0, 0.0, 406.0), (472.0, 330.0, 406.0), (314.0, 330.0, 456.0), (314.0, 0.0, 456.0)),
    ((314.0, 0.0, 456.0), (314.0, 330.0, 456.0), (265.0, 330.0, 296.0), (265.0, 0.0, 296.0)),
    ((265.0, 0.0, 296.0), (265.0, 330.0, 296.0), (423.0, 330.0, 247.0), (423.0, 0.0, 247.0)),
)
# fmt: on

# Camera: position, looking along +z with +y up; 35 mm lens on 25 mm x 25 mm film.
CAMERA_POSITION_MM = (278.0, 273.0, -800.0)
CAMERA_FOCAL_MM = 35.0
CAMERA_FILM_MM = 25.0

# Materials (linear RGB approximations of the measured spectra).
MATERIALS = {
    "white": {"baseColor": (0.725, 0.71, 0.68)},
    "red": {"baseColor": (0.63, 0.065, 0.05)},
    "green": {"baseColor": (0.14, 0.45, 0.091)},
    "light": {
        "baseColor": (0.78, 0.78, 0.78),
        "emissive": (1.0, 0.7059, 0.2353),
        "emissiveStrength": 17.0,
    },
}
MATERIAL_ORDER = ("white", "red", "green", "light")

MM_PER_M = 1000.0
GLTF_NAME = "cornell-box.gltf"
BIN_NAME = "cornell-box.bin"
EMISSIVE_STRENGTH_EXT = "KHR_materials_emissive_strength"

FLOAT = 5126
UNSIGNED_SHORT = 5123
UNSIGNED_INT = 5125
ARRAY_BUFFER = 34962
ELEMENT_ARRAY_BUFFER = 34963

Vec = tuple[float, float, float]


# --------------------------------------------------------------------------------------
# Small vector helpers (standard library only).
# --------------------------------------------------------------------------------------


def sub(a: Vec, b: Vec) -> Vec:
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def dot(a: Vec, b: Vec) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def cross(a: Vec, b: Vec) -> Vec:
    return (
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    )


def normalize(a: Vec) -> Vec:
    length = math.sqrt(dot(a, a))
    if length == 0.0:
        raise ValueError("degenerate normal")
    return (a[0] / length, a[1] / length, a[2] / length)


def mean(points) -> Vec:
    points = list(points)
    n = len(points)
    return (
        sum(p[0] for p in points) / n,
        sum(p[1] for p in points) / n,
        sum(p[2] for p in points) / n,
    )


def newell_normal(corners) -> Vec:
    """Unit normal of a (possibly slightly non-planar) polygon, following its winding."""
    nx = ny = nz = 0.0
    for i, p in enumerate(corners):
        q = corners[(i + 1) % len(corners)]
        nx += (p[1] - q[1]) * (p[2] + q[2])
        ny += (p[2] - q[2]) * (p[0] + q[0])
        nz += (p[0] - q[0]) * (p[1] + q[1])
    return normalize((nx, ny, nz))


def f32(x: float) -> float:
    """Round to the nearest float32 value."""
    return struct.unpack("<f", struct.pack("<f", x))[0]


def short_f32(x: float) -> float:
    """The shortest decimal that reads back as the same float32 (for tidy min/max)."""
    target = f32(x)
    for digits in range(1, 18):
        candidate = float(f"{target:.{digits}g}")
        if f32(candidate) == target:
            return candidate
    return target


# --------------------------------------------------------------------------------------
# Scene assembly.
# --------------------------------------------------------------------------------------


def surfaces() -> list[dict]:
    """All 16 quads with material, name and the direction their front face should face.

    'facing' is a function of the quad centroid (mm) returning a vector the front-face
    normal must have a positive dot product with.
    """
    room_points = [p for _, _, quad in ROOM_QUADS for p in quad]
    lo = tuple(min(p[i] for p in room_points) for i in range(3))
    hi = tuple(max(p[i] for p in room_points) for i in range(3))
    room_centre = tuple((lo[i] + hi[i]) / 2.0 for i in range(3))

    result = []
    for name, material, quad in ROOM_QUADS:
        result.append(
            {
                "name": name,
                "material": material,
                "corners": quad,
                "facing": ("towards", room_centre),
            }
        )
    light = tuple((x, y - LIGHT_DROP_MM, z) for x, y, z in LIGHT_QUAD)
    result.append(
        {
            "name": "light",
            "material": "light",
            "corners": light,
            "facing": ("direction", (0.0, -1.0, 0.0)),
        }
    )
    for block_name, block in (("short_block", SHORT_BLOCK), ("tall_block", TALL_BLOCK)):
        centre = mean(p for quad in block for p in quad)
        for i, quad in enumerate(block):
            result.append(
                {
                    "name": f"{block_name}_{i}",
                    "material": "white",
                    "corners": quad,
                    "facing": ("away_from", centre),
                }
            )
    return result


def intended_direction(surface: dict) -> Vec:
    kind, value = surface["facing"]
    centroid = mean(surface["corners"])
    if kind == "towards":
        return sub(value, centroid)
    if kind == "away_from":
        return sub(centroid, value)
    return value


def oriented_corners(surface: dict) -> tuple[Vec, ...]:
    """The quad's corners (in metres) in counter-clockwise order seen from the front."""
    corners = tuple(surface["corners"])
    if dot(newell_normal(corners), intended_direction(surface)) < 0.0:
        corners = (corners[0], corners[3], corners[2], corners[1])
    return tuple(tuple(c / MM_PER_M for c in p) for p in corners)


def camera_yfov() -> float:
    return 2.0 * math.atan((CAMERA_FILM_MM / 2.0) / CAMERA_FOCAL_MM)


def compact_json(document: dict) -> str:
    """Pretty-printed JSON with short numeric arrays kept on one line."""
    text = json.dumps(document, indent=2)

    def join(match: re.Match) -> str:
        items = [item.strip() for item in match.group(1).split(",")]
        return "[" + ", ".join(items) + "]"

    return (
        re.sub(r"\[\s*((?:-?[0-9][0-9.eE+-]*\s*,\s*)*-?[0-9][0-9.eE+-]*)\s*\]", join, text) + "\n"
    )


def build() -> tuple[dict, bytes]:
    """Return the glTF JSON document and the binary buffer."""
    by_material: dict[str, list[dict]] = {name: [] for name in MATERIAL_ORDER}
    for surface in surfaces():
        by_material[surface["material"]].append(surface)

    blob = bytearray()
    buffer_views: list[dict] = []
    accessors: list[dict] = []

    def add_view(data: bytes, target: int) -> int:
        while len(blob) % 4:
            blob.append(0)
        buffer_views.append(
            {
                "buffer": 0,
                "byteOffset": len(blob),
                "byteLength": len(data),
                "target": target,
            }
        )
        blob.extend(data)
        return len(buffer_views) - 1

    materials = []
    meshes = []
    nodes = []
    for material_index, material_name in enumerate(MATERIAL_ORDER):
        spec = MATERIALS[material_name]
        material = {
            "name": material_name,
            "pbrMetallicRoughness": {
                "baseColorFactor": [*spec["baseColor"], 1.0],
                "metallicFactor": 0.0,
                "roughnessFactor": 1.0,
            },
        }
        if "emissive" in spec:
            material["emissiveFactor"] = list(spec["emissive"])
            material["extensions"] = {
                EMISSIVE_STRENGTH_EXT: {"emissiveStrength": spec["emissiveStrength"]}
            }
        materials.append(material)

        positions: list[Vec] = []
        normals: list[Vec] = []
        indices: list[int] = []
        for surface in by_material[material_name]:
            corners = oriented_corners(surface)
            normal = newell_normal(corners)
            base = len(positions)
            positions.extend(corners)
            normals.extend([normal] * 4)
            indices.extend([base, base + 1, base + 2, base, base + 2, base + 3])

        index_type, index_format = (
            (UNSIGNED_SHORT, "H") if len(positions) <= 0xFFFF else (UNSIGNED_INT, "I")
        )
        pos_bytes = b"".join(struct.pack("<3f", *p) for p in positions)
        nrm_bytes = b"".join(struct.pack("<3f", *n) for n in normals)
        idx_bytes = struct.pack(f"<{len(indices)}{index_format}", *indices)

        stored = [struct.unpack("<3f", pos_bytes[i : i + 12]) for i in range(0, len(pos_bytes), 12)]
        accessors.append(
            {
                "bufferView": add_view(pos_bytes, ARRAY_BUFFER),
                "componentType": FLOAT,
                "count": len(positions),
                "type": "VEC3",
                "min": [short_f32(min(p[i] for p in stored)) for i in range(3)],
                "max": [short_f32(max(p[i] for p in stored)) for i in range(3)],
            }
        )
        accessors.append(
            {
                "bufferView": add_view(nrm_bytes, ARRAY_BUFFER),
                "componentType": FLOAT,
                "count": len(normals),
                "type": "VEC3",
            }
        )
        accessors.append(
            {
                "bufferView": add_view(idx_bytes, ELEMENT_ARRAY_BUFFER),
                "componentType": index_type,
                "count": len(indices),
                "type": "SCALAR",
            }
        )
        first = len(accessors) - 3
        meshes.append(
            {
                "name": material_name,
                "primitives": [
                    {
                        "attributes": {"POSITION": first, "NORMAL": first + 1},
                        "indices": first + 2,
                        "material": material_index,
                        "mode": 4,
                    }
                ],
            }
        )
        nodes.append({"name": material_name, "mesh": len(meshes) - 1})

    nodes.append(
        {
            "name": "camera",
            "camera": 0,
            "translation": [c / MM_PER_M for c in CAMERA_POSITION_MM],
            # glTF cameras look down their local -Z; turn 180 degrees about +Y to look along +z.
            "rotation": [0.0, 1.0, 0.0, 0.0],
        }
    )
    while len(blob) % 4:
        blob.append(0)

    document = {
        "asset": {
            "version": "2.0",
            "generator": "renderfarm examples/make_cornell_box.py",
            "copyright": "Geometry: Cornell University Program of Computer Graphics",
        },
        "extensionsUsed": [EMISSIVE_STRENGTH_EXT],
        "scene": 0,
        "scenes": [{"name": "Cornell box", "nodes": list(range(len(nodes)))}],
        "nodes": nodes,
        "cameras": [
            {
                "name": "camera",
                "type": "perspective",
                "perspective": {
                    "yfov": camera_yfov(),
                    "aspectRatio": 1.0,
                    "znear": 0.001,
                },
            }
        ],
        "meshes": meshes,
        "materials": materials,
        "accessors": accessors,
        "bufferViews": buffer_views,
        "buffers": [{"uri": BIN_NAME, "byteLength": len(blob)}],
    }
    return document, bytes(blob)


def write(out_dir: Path) -> None:
    document, blob = build()
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / BIN_NAME).write_bytes(blob)
    (out_dir / GLTF_NAME).write_text(compact_json(document), encoding="utf-8")


# --------------------------------------------------------------------------------------
# Verification of the written files.
# --------------------------------------------------------------------------------------

COMPONENTS = {"SCALAR": 1, "VEC3": 3}
FORMATS = {FLOAT: ("f", 4), UNSIGNED_SHORT: ("H", 2), UNSIGNED_INT: ("I", 4)}


def read_accessor(document: dict, blob: bytes, index: int, problems: list[str]) -> list[tuple]:
    accessor = document["accessors"][index]
    view = document["bufferViews"][accessor["bufferView"]]
    fmt, size = FORMATS[accessor["componentType"]]
    ncomp = COMPONENTS[accessor["type"]]
    start = view.get("byteOffset", 0) + accessor.get("byteOffset", 0)
    stride = view.get("byteStride", size * ncomp)
    end = start + stride * (accessor["count"] - 1) + size * ncomp
    if view.get("byteOffset", 0) % 4 or view["byteLength"] % 4 or start % size:
        problems.append(f"accessor {index}: bufferView not 4-byte aligned")
    if view.get("byteOffset", 0) + view["byteLength"] > len(blob):
        problems.append(f"accessor {index}: bufferView runs past the buffer")
        return []
    if end > view.get("byteOffset", 0) + view["byteLength"]:
        problems.append(f"accessor {index}: data runs past its bufferView")
        return []
    return [
        struct.unpack_from(f"<{ncomp}{fmt}", blob, start + i * stride)
        for i in range(accessor["count"])
    ]


def check(out_dir: Path) -> list[str]:
    """Re-read the written files; return a list of problems (empty if all is well)."""
    problems: list[str] = []
    document = json.loads((out_dir / GLTF_NAME).read_text(encoding="utf-8"))
    buffers = document.get("buffers", [])
    if len(buffers) != 1 or buffers[0].get("uri") != BIN_NAME:
        return [f"expected exactly one buffer with uri {BIN_NAME!r}"]
    blob = (out_dir / BIN_NAME).read_bytes()
    if len(blob) != buffers[0]["byteLength"] or len(blob) % 4:
        problems.append(
            f"{BIN_NAME}: {len(blob)} bytes, buffer byteLength "
            f"{buffers[0]['byteLength']} (must match and be a multiple of 4)"
        )
    if document.get("asset", {}).get("version") != "2.0":
        problems.append("asset.version is not 2.0")
    if EMISSIVE_STRENGTH_EXT not in document.get("extensionsUsed", []):
        problems.append(f"{EMISSIVE_STRENGTH_EXT} missing from extensionsUsed")

    expected = {name: [] for name in MATERIAL_ORDER}
    for surface in surfaces():
        expected[surface["material"]].append(surface)

    total_quads = total_triangles = 0
    materials = document.get("materials", [])
    for mesh_index, mesh in enumerate(document.get("meshes", [])):
        for prim_index, prim in enumerate(mesh["primitives"]):
            where = f"mesh {mesh_index} ({mesh.get('name')}) primitive {prim_index}"
            material = materials[prim["material"]]
            name = material.get("name")
            if name not in MATERIALS:
                problems.append(f"{where}: unknown material {name!r}")
                continue
            pbr = material.get("pbrMetallicRoughness", {})
            spec = MATERIALS[name]
            if pbr.get("baseColorFactor") != [*spec["baseColor"], 1.0]:
                problems.append(f"{where}: wrong baseColorFactor")
            if pbr.get("metallicFactor") != 0.0 or pbr.get("roughnessFactor") != 1.0:
                problems.append(f"{where}: metallic must be 0 and roughness 1")
            if "emissive" in spec:
                strength = material.get("extensions", {}).get(EMISSIVE_STRENGTH_EXT, {})
                if (
                    material.get("emissiveFactor") != list(spec["emissive"])
                    or strength.get("emissiveStrength") != spec["emissiveStrength"]
                ):
                    problems.append(f"{where}: wrong emission")
            if prim.get("mode", 4) != 4:
                problems.append(f"{where}: not a triangle list")

            pos_accessor = document["accessors"][prim["attributes"]["POSITION"]]
            positions = read_accessor(document, blob, prim["attributes"]["POSITION"], problems)
            normals = read_accessor(document, blob, prim["attributes"]["NORMAL"], problems)
            indices = [i[0] for i in read_accessor(document, blob, prim["indices"], problems)]
            if not positions or len(normals) != len(positions) or len(indices) % 3:
                problems.append(f"{where}: inconsistent attribute/index counts")
                continue

            for axis in range(3):
                lo = min(p[axis] for p in positions)
                hi = max(p[axis] for p in positions)
                if f32(pos_accessor["min"][axis]) != lo or f32(pos_accessor["max"][axis]) != hi:
                    problems.append(f"{where}: POSITION min/max do not match the data")
                    break
            for n in normals:
                if abs(math.sqrt(dot(n, n)) - 1.0) > 1e-6:
                    problems.append(f"{where}: normal {n} is not unit length")
                    break
            if any(i >= len(positions) for i in indices):
                problems.append(f"{where}: index out of range")
                continue

            quads = expected[name]
            if len(positions) != 4 * len(quads) or len(indices) != 6 * len(quads):
                problems.append(f"{where}: expected {len(quads)} quads")
                continue
            for q, surface in enumerate(quads):
                want = sorted(tuple(f32(c / MM_PER_M) for c in p) for p in surface["corners"])
                have = sorted(positions[4 * q : 4 * q + 4])
                if want != have:
                    problems.append(f"{where}: {surface['name']} corners differ from the table")
                facing = intended_direction(surface)
                for t in (2 * q, 2 * q + 1):
                    tri = indices[3 * t : 3 * t + 3]
                    if any(not 4 * q <= i < 4 * q + 4 for i in tri):
                        problems.append(f"{where}: triangle {t} mixes quads")
                        continue
                    p0, p1, p2 = (positions[i] for i in tri)
                    geometric = normalize(cross(sub(p1, p0), sub(p2, p0)))
                    if dot(geometric, facing) <= 0.0:
                        problems.append(
                            f"{where}: {surface['name']} triangle {t} faces the wrong way"
                        )
                    if any(dot(geometric, normals[i]) < 0.999 for i in tri):
                        problems.append(
                            f"{where}: {surface['name']} triangle {t} normals "
                            "disagree with its winding"
                        )
                total_triangles += 2
            total_quads += len(quads)

    if total_quads != 16 or total_triangles != 32:
        problems.append(
            f"expected 16 quads / 32 triangles, found {total_quads} / {total_triangles}"
        )

    cameras = [n for n in document.get("nodes", []) if "camera" in n]
    if len(cameras) != 1:
        problems.append("expected exactly one camera node")
    else:
        node = cameras[0]
        want_t = [c / MM_PER_M for c in CAMERA_POSITION_MM]
        if node.get("rotation") != [0.0, 1.0, 0.0, 0.0] or node.get("translation") != want_t:
            problems.append("camera node transform is wrong")
        persp = document["cameras"][node["camera"]].get("perspective", {})
        if (
            abs(persp.get("yfov", 0.0) - camera_yfov()) > 1e-12
            or persp.get("aspectRatio") != 1.0
            or persp.get("znear") != 0.001
        ):
            problems.append("camera projection is wrong")
    return problems


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--out-dir",
        type=Path,
        default=Path(__file__).resolve().parent,
        help="directory for cornell-box.gltf/.bin (default: next to this script)",
    )
    parser.add_argument(
        "--check", action="store_true", help="only verify the already written files"
    )
    args = parser.parse_args(argv)

    if not args.check:
        write(args.out_dir)
        print(f"wrote {args.out_dir / GLTF_NAME} and {args.out_dir / BIN_NAME}")
    problems = check(args.out_dir)
    for problem in problems:
        print(f"FAIL: {problem}", file=sys.stderr)
    if problems:
        return 1
    print("check passed: 16 quads, 32 triangles, windings, normals and bounds are consistent")
    return 0


if __name__ == "__main__":
    sys.exit(main())
