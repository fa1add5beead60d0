#!/usr/bin/env python3
"""Write a short animated glTF 2.0 scene, hinged-box.glb: a chest whose lid swings open on its
hinge, a skinned stalk that bends beside it, and a camera that dollies round them, 2 seconds
at 24 fps (frames 1-48: Blender's exporter's timing, frame f at f / 24 s).

What it exercises of glTF animation (3.11): a rigid child node rotating about its hinge (LINEAR
quaternion keys), a skin of three joints whose rotations follow CUBICSPLINE keys with
tangents, a camera node with LINEAR translation and rotation keys, and holds before the first
and after the last keyframe. Lighting is one emissive quad (KHR_materials_emissive_strength)
above the scene.

Usage:
    python make_hinged_box.py                # write hinged-box.glb next to this script
    python make_hinged_box.py -o OUT.glb     # write it elsewhere
    renderfarm render examples/hinged-box.glb --frames 1-48 -o out/hinge_####.exr \\
        --movie out/hinge.mp4 --width 320 --height 240 --max-spp 128

Only the standard library is used, so any Python 3.10+ runs it.
"""

from __future__ import annotations

import argparse
import json
import math
import struct
from pathlib import Path

FPS = 24
FRAMES = 48  # the animation ends at FRAMES / FPS = 2 s
END = FRAMES / FPS


# ---- vector helpers (tuples of floats)


def sub(a, b):
    return tuple(x - y for x, y in zip(a, b, strict=True))


def cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def normalize(v):
    n = math.sqrt(sum(x * x for x in v))
    return tuple(x / n for x in v)


def quat_axis_angle(axis, angle):
    axis = normalize(axis)
    s = math.sin(angle / 2)
    return (axis[0] * s, axis[1] * s, axis[2] * s, math.cos(angle / 2))


def quat_mul(a, b):
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    )


def look_rotation(eye, target):
    """The rotation that turns a glTF camera (looking down -Z, +Y up) from eye toward target:
    yaw about +Y, then pitch about the camera's +X."""
    d = normalize(sub(target, eye))
    yaw = math.atan2(-d[0], -d[2])
    pitch = math.asin(max(-1.0, min(1.0, d[1])))
    return quat_mul(quat_axis_angle((0, 1, 0), yaw), quat_axis_angle((1, 0, 0), pitch))


# ---- the buffer: accessors appended one after another


class Buffer:
    def __init__(self):
        self.data = bytearray()
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def add(self, rows, gltf_type, component=5126, target=None):
        """rows: a list of tuples (or numbers for SCALAR); float32 unless component says."""
        fmt = {5126: "f", 5123: "H", 5121: "B"}[component]
        width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}[gltf_type]
        flat = [x for r in rows for x in (r if isinstance(r, tuple | list) else (r,))]
        assert len(flat) == width * len(rows)
        while len(self.data) % 4:
            self.data.append(0)
        view = {"buffer": 0, "byteOffset": len(self.data), "byteLength": 0}
        self.data += struct.pack(f"<{len(flat)}{fmt}", *flat)
        view["byteLength"] = len(self.data) - view["byteOffset"]
        if target is not None:
            view["target"] = target
        self.views.append(view)
        accessor = {
            "bufferView": len(self.views) - 1,
            "componentType": component,
            "count": len(rows),
            "type": gltf_type,
        }
        if gltf_type in ("SCALAR", "VEC3") and component == 5126:
            cols = [flat[i::width] for i in range(width)]
            accessor["min"] = [min(c) for c in cols]
            accessor["max"] = [max(c) for c in cols]
        self.accessors.append(accessor)
        return len(self.accessors) - 1


# ---- meshes


def box(lo, hi):
    """A closed box as 6 quads with outward normals: positions, normals, indices."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    faces = [
        ((x0, y0, z1), (x1, y0, z1), (x1, y1, z1), (x0, y1, z1)),  # +z
        ((x1, y0, z0), (x0, y0, z0), (x0, y1, z0), (x1, y1, z0)),  # -z
        ((x1, y0, z1), (x1, y0, z0), (x1, y1, z0), (x1, y1, z1)),  # +x
        ((x0, y0, z0), (x0, y0, z1), (x0, y1, z1), (x0, y1, z0)),  # -x
        ((x0, y1, z1), (x1, y1, z1), (x1, y1, z0), (x0, y1, z0)),  # +y
        ((x0, y0, z0), (x1, y0, z0), (x1, y0, z1), (x0, y0, z1)),  # -y
    ]
    return quads(faces)


def quads(faces):
    positions, normals, indices = [], [], []
    for q in faces:
        n = normalize(cross(sub(q[1], q[0]), sub(q[2], q[0])))
        base = len(positions)
        positions += list(q)
        normals += [n] * 4
        indices += [base, base + 1, base + 2, base, base + 2, base + 3]
    return positions, normals, indices


STALK_HEIGHT = 1.2
STALK_RADIUS = 0.07
STALK_LEVELS = 24
STALK_SIDES = 12
JOINT_HEIGHTS = (0.0, 0.4, 0.8)


def stalk():
    """A capped cylinder along +y, skinned to the three joints: each vertex is weighted
    between the two joints around its height (linearly), so the stalk bends smoothly."""
    positions, normals, joints, weights, indices = [], [], [], [], []
    for level in range(STALK_LEVELS + 1):
        y = STALK_HEIGHT * level / STALK_LEVELS
        r = STALK_RADIUS * (1.0 - 0.6 * y / STALK_HEIGHT)  # tapering to the top
        for side in range(STALK_SIDES):
            a = 2 * math.pi * side / STALK_SIDES
            positions.append((r * math.cos(a), y, r * math.sin(a)))
            normals.append((math.cos(a), 0.0, math.sin(a)))
            j, w = stalk_influence(y)
            joints.append(j)
            weights.append(w)
    for level in range(STALK_LEVELS):
        for side in range(STALK_SIDES):
            a = level * STALK_SIDES + side
            b = level * STALK_SIDES + (side + 1) % STALK_SIDES
            c, d = a + STALK_SIDES, b + STALK_SIDES
            indices += [a, c, b, b, c, d]  # counter-clockwise seen from outside
    top = len(positions)  # the cap: a fan round its centre, facing up
    positions.append((0.0, STALK_HEIGHT, 0.0))
    normals.append((0.0, 1.0, 0.0))
    j, w = stalk_influence(STALK_HEIGHT)
    joints.append(j)
    weights.append(w)
    ring = STALK_LEVELS * STALK_SIDES
    for side in range(STALK_SIDES):
        indices += [top, ring + (side + 1) % STALK_SIDES, ring + side]
    return positions, normals, joints, weights, indices


def stalk_influence(y):
    """JOINTS_0 and WEIGHTS_0 of a vertex at height y (weights sum to 1)."""
    if y >= JOINT_HEIGHTS[-1]:
        return (2, 0, 0, 0), (1.0, 0.0, 0.0, 0.0)
    for k in range(len(JOINT_HEIGHTS) - 1):
        lo, hi = JOINT_HEIGHTS[k], JOINT_HEIGHTS[k + 1]
        if y < hi:
            s = (y - lo) / (hi - lo)
            return (k, k + 1, 0, 0), (1.0 - s, s, 0.0, 0.0)
    raise AssertionError(y)


# ---- the scene


def build() -> tuple[dict, bytes]:
    buf = Buffer()
    meshes, materials, nodes = [], [], []

    def material(name, color, roughness, metallic=0.0, emissive=None, strength=None):
        m = {
            "name": name,
            "pbrMetallicRoughness": {
                "baseColorFactor": [*color, 1.0],
                "roughnessFactor": roughness,
                "metallicFactor": metallic,
            },
        }
        if emissive is not None:
            m["emissiveFactor"] = list(emissive)
            m["extensions"] = {"KHR_materials_emissive_strength": {"emissiveStrength": strength}}
        materials.append(m)
        return len(materials) - 1

    def mesh(name, geometry, mat, skin_attributes=None):
        positions, normals, indices = geometry
        attributes = {
            "POSITION": buf.add(positions, "VEC3", target=34962),
            "NORMAL": buf.add(normals, "VEC3", target=34962),
        }
        if skin_attributes is not None:
            j, w = skin_attributes
            attributes["JOINTS_0"] = buf.add(j, "VEC4", component=5121, target=34962)
            attributes["WEIGHTS_0"] = buf.add(w, "VEC4", target=34962)
        primitive = {
            "attributes": attributes,
            "indices": buf.add(indices, "SCALAR", component=5123, target=34963),
            "material": mat,
        }
        meshes.append({"name": name, "primitives": [primitive]})
        return len(meshes) - 1

    def node(**fields):
        nodes.append(fields)
        return len(nodes) - 1

    grey = material("floor", (0.6, 0.6, 0.6), 0.8)
    wall = material("wall", (0.7, 0.68, 0.62), 0.9)
    wood = material("chest", (0.55, 0.27, 0.1), 0.5)
    brass = material("lid", (0.9, 0.65, 0.3), 0.3, metallic=1.0)
    teal = material("stalk", (0.1, 0.45, 0.5), 0.4)
    lamp = material("lamp", (0.0, 0.0, 0.0), 1.0, emissive=(1.0, 0.92, 0.8), strength=12.0)

    floor = quads([((-6, 0, 6), (6, 0, 6), (6, 0, -6), (-6, 0, -6))])
    back = quads([((-6, 0, -1.5), (6, 0, -1.5), (6, 4, -1.5), (-6, 4, -1.5))])
    light = quads([((-0.6, 2.6, -0.6), (0.6, 2.6, -0.6), (0.6, 2.6, 0.6), (-0.6, 2.6, 0.6))])
    roots = [
        node(name="floor", mesh=mesh("floor", floor, grey)),
        node(name="back wall", mesh=mesh("back wall", back, wall)),
        node(name="lamp", mesh=mesh("lamp", light, lamp)),
    ]

    # The chest: its body at the origin, the lid a child node whose origin is the hinge (the
    # body's top back edge), so rotating the lid node about +x swings it open.
    body = mesh("chest", box((-0.35, 0.0, -0.22), (0.35, 0.4, 0.22)), wood)
    lid_mesh = mesh("lid", box((-0.37, 0.0, 0.0), (0.37, 0.06, 0.46)), brass)
    lid = node(name="lid", mesh=lid_mesh, translation=[0.0, 0.4, -0.23])
    chest = node(name="chest", mesh=body, translation=[-0.45, 0.0, 0.0], children=[lid])
    roots.append(chest)

    # The stalk: a skin of three joints in a chain (root, middle, tip).
    positions, normals, joints, weights, indices = stalk()
    stalk_mesh = mesh("stalk", (positions, normals, indices), teal, (joints, weights))
    joint_nodes = []
    for k, h in enumerate(JOINT_HEIGHTS):
        parent_h = JOINT_HEIGHTS[k - 1] if k else 0.0
        joint_nodes.append(node(name=f"stalk joint {k}", translation=[0.0, h - parent_h, 0.0]))
    for parent, child in zip(joint_nodes, joint_nodes[1:], strict=False):
        nodes[parent]["children"] = [child]
    # Inverse bind matrices: the joints' bind poses are pure translations up the stalk.
    ibm = []
    for h in JOINT_HEIGHTS:
        m = [1.0, 0, 0, 0, 0, 1.0, 0, 0, 0, 0, 1.0, 0, 0, -h, 0, 1.0]  # column-major
        ibm.append(tuple(m))
    skin = {"joints": joint_nodes, "inverseBindMatrices": buf.add(ibm, "MAT4"),
            "skeleton": joint_nodes[0]}  # fmt: skip
    stalk_root = node(name="stalk", translation=[0.55, 0.0, 0.1], children=[joint_nodes[0]])
    stalk_skinned = node(name="stalk skin", mesh=stalk_mesh, skin=0)
    roots += [stalk_root, stalk_skinned]

    # The camera: dollies from the left front to the right, looking at the chest and stalk.
    target = (0.0, 0.45, 0.0)
    eyes = [(-1.2, 1.1, 2.6), (0.0, 1.25, 2.9), (1.3, 1.0, 2.5)]
    cam = node(name="camera", camera=0, translation=list(eyes[0]),
               rotation=list(look_rotation(eyes[0], target)))  # fmt: skip
    roots.append(cam)

    # ---- animations: one, "action", of every channel.
    samplers, channels = [], []

    def channel(node_index, path, times, values, gltf_type, interpolation="LINEAR"):
        samplers.append({
            "input": buf.add(times, "SCALAR"),
            "output": buf.add(values, gltf_type),
            "interpolation": interpolation,
        })  # fmt: skip
        channels.append({"sampler": len(samplers) - 1,
                         "target": {"node": node_index, "path": path}})  # fmt: skip

    # The lid: closed until 0.25 s, open by 110 degrees at 1.5 s, held open after.
    lid_times = [0.25, 0.9, 1.5]
    lid_angles = [0.0, -1.2, -1.92]
    channel(lid, "rotation", lid_times,
            [quat_axis_angle((1, 0, 0), a) for a in lid_angles], "VEC4")  # fmt: skip

    # The stalk's middle and tip joints sway about z: CUBICSPLINE keys (in-tangent, value,
    # out-tangent per key) of a quarter-period sine, with tangents in radians per second.
    sway_times = [0.0, 0.5, 1.0, 1.5, 2.0]
    amplitude, omega = 0.6, 2 * math.pi / 2.0  # one full sway in the 2 seconds
    for joint, scale in ((joint_nodes[1], 1.0), (joint_nodes[2], 0.8)):
        values = []
        for t in sway_times:
            angle = scale * amplitude * math.sin(omega * t)
            rate = scale * amplitude * omega * math.cos(omega * t)  # d angle / dt
            q = quat_axis_angle((0, 0, 1), angle)
            # dq/dt of a rotation about a fixed axis: (axis sin'(a/2), cos'(a/2)) * rate / 2
            dq = (0.0, 0.0, math.cos(angle / 2) * rate / 2, -math.sin(angle / 2) * rate / 2)
            values += [dq, q, dq]
        channel(joint, "rotation", sway_times, values, "VEC4", "CUBICSPLINE")

    cam_times = [1 / FPS, END / 2, END]
    channel(cam, "translation", cam_times, [tuple(e) for e in eyes], "VEC3")
    channel(cam, "rotation", cam_times, [look_rotation(e, target) for e in eyes], "VEC4")

    doc = {
        "asset": {"version": "2.0", "generator": "renderfarm examples/make_hinged_box.py"},
        "extensionsUsed": ["KHR_materials_emissive_strength"],
        "scene": 0,
        "scenes": [{"name": "hinged box", "nodes": roots}],
        "nodes": nodes,
        "meshes": meshes,
        "materials": materials,
        "skins": [skin],
        "cameras": [{"type": "perspective", "perspective": {
            "yfov": math.radians(40.0), "aspectRatio": 4 / 3, "znear": 0.05, "zfar": 50.0}}],
        "animations": [{"name": "action", "samplers": samplers, "channels": channels}],
        "bufferViews": buf.views,
        "accessors": buf.accessors,
        "buffers": [{"byteLength": len(buf.data)}],
    }  # fmt: skip
    return doc, bytes(buf.data)


def glb(doc: dict, binary: bytes) -> bytes:
    """The GLB container (glTF 2.0, 4.4): header, JSON chunk, BIN chunk, each 4-byte aligned."""
    text = json.dumps(doc, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    binary += b"\0" * (-len(binary) % 4)
    total = 12 + 8 + len(text) + 8 + len(binary)
    out = struct.pack("<4sII", b"glTF", 2, total)
    out += struct.pack("<I4s", len(text), b"JSON") + text
    out += struct.pack("<I4s", len(binary), b"BIN\0") + binary
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    default = Path(__file__).resolve().with_name("hinged-box.glb")
    parser.add_argument("-o", "--output", type=Path, default=default, help="the .glb to write")
    args = parser.parse_args()
    doc, binary = build()
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_bytes(glb(doc, binary))
    print(args.output)


if __name__ == "__main__":
    main()
