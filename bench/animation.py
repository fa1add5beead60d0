"""Animated scenes: what moving from one frame to the next costs the worker.

Writes a .glb to a temporary directory (numpy-built): a static wavy floor of many triangles
under a lamp, a lid on a hinge (a rigid mesh whose parent's rotation is animated: an Embree
instance), a tentacle skinned to a chain of joints that bend over time (its vertices rewritten
and its BVH refit every frame) and a camera moving on an arc. Renders BENCH_FRAMES frames of
it with one `renderfarm-worker render --times ...` (one load, one pose per frame, as a farm
worker does between frames) at BENCH_SIZE x BENCH_SIZE and BENCH_SPP samples per pixel, and
reports per frame the scene update (posing: animation, skinning, refit, top-level build) and
the render time, their ratio (goal: update under 5% of the render), frames per hour, and the
one-time load (parse and static part). Writes bench/results/animation.json.

Environment: RENDERFARM_WORKER (binary, default build/worker/renderfarm-worker), BENCH_SIZE
(default 512), BENCH_SPP (64), BENCH_FRAMES (6), BENCH_THREADS (2), BENCH_GRID (floor quads
per side, 500: 0.5M triangles), BENCH_RINGS (tentacle rings, 400: 51K triangles),
BENCH_SHUTTER (OPEN,CLOSE: motion blur over that shutter at 24 fps, written to
bench/results/animation_blur.json; default none).
"""

from __future__ import annotations

import json
import os
import struct
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from support.results import write_results  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
TARGET_UPDATE_SHARE = 0.05
FPS = 24.0


class Glb:
    """Buffer views and accessors of one GLB binary chunk."""

    def __init__(self) -> None:
        self.blobs: list[bytes] = []
        self.views: list[dict] = []
        self.accessors: list[dict] = []
        self.offset = 0

    def add(self, array: np.ndarray, kind: str, ctype: int = 5126, bounds: bool = False) -> int:
        data = np.ascontiguousarray(array).tobytes()
        self.views.append({"buffer": 0, "byteOffset": self.offset, "byteLength": len(data)})
        pad = -len(data) % 4
        self.blobs.append(data + b"\0" * pad)
        self.offset += len(data) + pad
        count = len(array) if array.ndim > 1 or kind == "SCALAR" else 1
        acc = {
            "bufferView": len(self.views) - 1,
            "componentType": ctype,
            "count": count,
            "type": kind,
        }
        if bounds:
            flat = array.reshape(count, -1)
            acc["min"], acc["max"] = flat.min(0).tolist(), flat.max(0).tolist()
        self.accessors.append(acc)
        return len(self.accessors) - 1

    def write(self, doc: dict, path: Path) -> None:
        binary = b"".join(self.blobs)
        doc.update(
            accessors=self.accessors, bufferViews=self.views, buffers=[{"byteLength": len(binary)}]
        )
        text = json.dumps(doc).encode()
        text += b" " * (-len(text) % 4)
        with open(path, "wb") as f:
            f.write(struct.pack("<III", 0x46546C67, 2, 12 + 8 + len(text) + 8 + len(binary)))
            f.write(struct.pack("<II", len(text), 0x4E4F534A) + text)
            f.write(struct.pack("<II", len(binary), 0x004E4942) + binary)


def quat(axis: tuple[float, float, float], angle: np.ndarray) -> np.ndarray:
    """Unit quaternions (x, y, z, w) of rotations by angle about axis."""
    a = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    s, c = np.sin(angle / 2), np.cos(angle / 2)
    return np.stack([a[0] * s, a[1] * s, a[2] * s, c], -1).astype(np.float32)


def floor_mesh(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    xs = np.linspace(-4.0, 4.0, n + 1, dtype=np.float32)
    x, z = np.meshgrid(xs, xs)
    y = (0.04 * np.sin(5 * x) * np.cos(5 * z)).astype(np.float32)
    pos = np.stack([x, y, z], -1).reshape(-1, 3)
    nrm = np.stack(
        [
            -0.2 * np.cos(5 * x) * np.cos(5 * z),
            np.ones_like(x),
            0.2 * np.sin(5 * x) * np.sin(5 * z),
        ],
        -1,
    ).reshape(-1, 3)
    nrm = (nrm / np.linalg.norm(nrm, axis=1, keepdims=True)).astype(np.float32)
    i = np.arange(n, dtype=np.uint32)
    a = (i[:, None] * (n + 1) + i[None, :]).ravel()
    b, c = a + 1, a + n + 1
    idx = np.stack([a, c, b, b, c, c + 1], -1).reshape(-1).astype(np.uint32)
    return pos, nrm, idx


def box_mesh(size: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A box from (0, 0, 0) to size: 6 faces of 2 triangles, outward normals."""
    sx, sy, sz = size
    pos, nrm, idx = [], [], []
    for axis in range(3):
        for side in (0.0, 1.0):
            n = np.zeros(3)
            n[axis] = 1.0 if side else -1.0
            u, v = [k for k in range(3) if k != axis]
            corners = []
            for cu, cv in ((0, 0), (1, 0), (1, 1), (0, 1)):
                p = np.zeros(3)
                p[axis], p[u], p[v] = side, cu, cv
                corners.append(p * (sx, sy, sz))
            base = len(pos)
            pos += corners
            nrm += [n] * 4
            tri = [0, 1, 2, 0, 2, 3]
            if np.dot(np.cross(corners[1] - corners[0], corners[2] - corners[0]), n) < 0:
                tri = [0, 2, 1, 0, 3, 2]
            idx += [base + t for t in tri]
    return np.array(pos, np.float32), np.array(nrm, np.float32), np.array(idx, np.uint32)


def tentacle(rings: int, segments: int, joints: int, length: float):
    """A tapered tube along +y of rings x segments vertices, each vertex skinned to the two
    joints of the chain nearest its height (linear blend)."""
    t = np.linspace(0.0, 1.0, rings, dtype=np.float32)
    phi = np.linspace(0.0, 2 * np.pi, segments, endpoint=False, dtype=np.float32)
    radius = 0.18 * (1.0 - 0.7 * t)
    y = t * length
    pos = np.stack(
        [
            radius[:, None] * np.cos(phi)[None, :],
            np.repeat(y[:, None], segments, 1),
            radius[:, None] * np.sin(phi)[None, :],
        ],
        -1,
    ).reshape(-1, 3)
    nrm = np.stack(
        [
            np.cos(phi)[None, :].repeat(rings, 0),
            np.zeros((rings, segments)),
            np.sin(phi)[None, :].repeat(rings, 0),
        ],
        -1,
    ).reshape(-1, 3)
    r = np.arange(rings - 1, dtype=np.uint32)[:, None]
    s = np.arange(segments, dtype=np.uint32)[None, :]
    a = r * segments + s
    b = r * segments + (s + 1) % segments
    c, d = a + segments, b + segments
    idx = np.stack([a, c, b, b, c, d], -1).reshape(-1).astype(np.uint32)
    # Joint k sits at height k * length / (joints - 1) (a chain, each the child of the last).
    h = t * (joints - 1)
    j0 = np.minimum(np.floor(h), joints - 2).astype(np.uint16)
    w1 = (h - j0).astype(np.float32)
    jnt = np.zeros((rings, 4), np.uint16)
    jnt[:, 0], jnt[:, 1] = j0, j0 + 1
    wgt = np.zeros((rings, 4), np.float32)
    wgt[:, 0], wgt[:, 1] = 1.0 - w1, w1
    jnt = np.repeat(jnt, segments, 0)
    wgt = np.repeat(wgt, segments, 0)
    return pos.astype(np.float32), nrm.astype(np.float32), idx, jnt, wgt


def write_scene(path: Path, grid: int, rings: int, frames: int) -> dict:
    glb = Glb()
    duration = max(frames - 1, 1) / FPS
    fp, fn, fi = floor_mesh(grid)
    floor = {"POSITION": glb.add(fp, "VEC3", bounds=True), "NORMAL": glb.add(fn, "VEC3")}
    floor_idx = glb.add(fi, "SCALAR", 5125)
    bp, bn, bi = box_mesh((1.2, 0.6, 0.9))
    base_attrs = {"POSITION": glb.add(bp, "VEC3", bounds=True), "NORMAL": glb.add(bn, "VEC3")}
    base_idx = glb.add(bi, "SCALAR", 5125)
    lp, ln, li = box_mesh((1.2, 0.08, 0.9))
    lid_attrs = {"POSITION": glb.add(lp, "VEC3", bounds=True), "NORMAL": glb.add(ln, "VEC3")}
    lid_idx = glb.add(li, "SCALAR", 5125)
    lamp = np.array([[-1, 3, -1], [1, 3, -1], [-1, 3, 1], [1, 3, 1]], np.float32)
    lamp_pos = glb.add(lamp, "VEC3", bounds=True)
    lamp_idx = glb.add(np.array([0, 1, 2, 1, 3, 2], np.uint32), "SCALAR", 5125)  # faces -y
    joints = 8
    tp, tn, ti, tj, tw = tentacle(rings, 64, joints, 2.0)
    tentacle_attrs = {
        "POSITION": glb.add(tp, "VEC3", bounds=True),
        "NORMAL": glb.add(tn, "VEC3"),
        "JOINTS_0": glb.add(tj, "VEC4", 5123),
        "WEIGHTS_0": glb.add(tw, "VEC4"),
    }
    tentacle_idx = glb.add(ti, "SCALAR", 5125)
    ibm = np.zeros((joints, 16), np.float32)
    for k in range(joints):
        m = np.eye(4, dtype=np.float32)
        m[3, 1] = -k * 2.0 / (joints - 1)  # column-major: the translation is the last column
        ibm[k] = m.reshape(-1)
    ibm_acc = glb.add(ibm, "MAT4")
    keys = np.linspace(0.0, duration, 9, dtype=np.float32)
    key_acc = glb.add(keys, "SCALAR", bounds=True)
    phase = keys / max(duration, 1e-6) * 2 * np.pi
    hinge_acc = glb.add(quat((1, 0, 0), -1.1 * (0.5 - 0.5 * np.cos(phase))), "VEC4")
    bend_accs = [
        glb.add(quat((0, 0, 1), 0.25 * np.sin(phase + 0.6 * k)), "VEC4") for k in range(1, joints)
    ]
    # The camera circles the middle of the scene: positions on an arc, turned to face it.
    angle = 0.35 * np.sin(phase)
    cam_pos = np.stack([5.0 * np.sin(angle), np.full_like(angle, 2.2), 5.0 * np.cos(angle)], -1)
    cam_rot = quat((0, 1, 0), angle)
    tilt = quat((1, 0, 0), np.full_like(angle, -0.3))[0]

    def mul(q: np.ndarray, r: np.ndarray) -> np.ndarray:  # Hamilton product, (x, y, z, w)
        x1, y1, z1, w1 = np.moveaxis(q, -1, 0)
        x2, y2, z2, w2 = r
        return np.stack(
            [
                w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
                w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            ],
            -1,
        ).astype(np.float32)

    cam_t_acc = glb.add(cam_pos.astype(np.float32), "VEC3")
    cam_r_acc = glb.add(mul(cam_rot, tilt), "VEC4")
    # Nodes: 0 floor, 1 lamp, 2 box base, 3 hinge (animated) -> 4 lid, 5 tentacle mesh,
    # 6.. joints (chain), then the camera.
    first_joint = 6
    nodes = [
        {"mesh": 0},
        {"mesh": 1},
        {"mesh": 2, "translation": [-2.0, 0.0, -0.5]},
        {"translation": [-2.0, 0.6, -0.5], "children": [4]},
        {"mesh": 3},
        {"mesh": 4, "skin": 0},
    ]
    for k in range(joints):
        node = {"translation": [1.2, 0.0, 0.0] if k == 0 else [0.0, 2.0 / (joints - 1), 0.0]}
        if k + 1 < joints:
            node["children"] = [first_joint + k + 1]
        nodes.append(node)
    camera_node = len(nodes)
    nodes.append({"camera": 0})
    channels = [
        {"sampler": 0, "target": {"node": 3, "path": "rotation"}},
        {"sampler": 1, "target": {"node": camera_node, "path": "translation"}},
        {"sampler": 2, "target": {"node": camera_node, "path": "rotation"}},
    ]
    samplers = [
        {"input": key_acc, "output": hinge_acc},
        {"input": key_acc, "output": cam_t_acc},
        {"input": key_acc, "output": cam_r_acc},
    ]
    for k, acc in enumerate(bend_accs, start=1):
        channels.append(
            {"sampler": len(samplers), "target": {"node": first_joint + k, "path": "rotation"}}
        )
        samplers.append({"input": key_acc, "output": acc})
    grey = {"pbrMetallicRoughness": {"baseColorFactor": [0.7, 0.7, 0.7, 1], "metallicFactor": 0}}
    doc = {
        "asset": {"version": "2.0", "generator": "bench/animation.py"},
        "extensionsUsed": ["KHR_materials_emissive_strength"],
        "scene": 0,
        "scenes": [{"nodes": [0, 1, 2, 3, 5, first_joint, camera_node]}],
        "nodes": nodes,
        "cameras": [{"type": "perspective", "perspective": {"yfov": 0.75, "znear": 0.01}}],
        "skins": [
            {
                "joints": list(range(first_joint, first_joint + joints)),
                "inverseBindMatrices": ibm_acc,
                "skeleton": first_joint,
            }
        ],
        "materials": [
            grey,
            {
                "emissiveFactor": [1, 1, 1],
                "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": 12}},
            },
            {
                "pbrMetallicRoughness": {
                    "baseColorFactor": [0.8, 0.35, 0.2, 1],
                    "metallicFactor": 0,
                    "roughnessFactor": 0.4,
                }
            },
            {
                "pbrMetallicRoughness": {
                    "baseColorFactor": [0.2, 0.5, 0.8, 1],
                    "metallicFactor": 0,
                    "roughnessFactor": 0.6,
                }
            },
        ],
        "meshes": [
            {"primitives": [{"attributes": floor, "indices": floor_idx, "material": 0}]},
            {
                "primitives": [
                    {"attributes": {"POSITION": lamp_pos}, "indices": lamp_idx, "material": 1}
                ]
            },
            {"primitives": [{"attributes": base_attrs, "indices": base_idx, "material": 2}]},
            {"primitives": [{"attributes": lid_attrs, "indices": lid_idx, "material": 2}]},
            {
                "primitives": [
                    {"attributes": tentacle_attrs, "indices": tentacle_idx, "material": 3}
                ]
            },
        ],
        "animations": [{"name": "bench", "channels": channels, "samplers": samplers}],
    }
    glb.write(doc, path)
    return {
        "static_triangles": len(fi) // 3 + len(bi) // 3 + 2,
        "rigid_triangles": len(li) // 3,
        "skinned_triangles": len(ti) // 3,
        "joints": joints,
    }


def main() -> dict:
    binary = Path(os.environ.get("RENDERFARM_WORKER", ROOT / "build/worker/renderfarm-worker"))
    if not binary.exists():
        sys.exit(f"{binary} not found: build the worker first (make worker)")
    size = int(os.environ.get("BENCH_SIZE", "512"))
    spp = int(os.environ.get("BENCH_SPP", "64"))
    frames = int(os.environ.get("BENCH_FRAMES", "6"))
    threads = os.environ.get("BENCH_THREADS", "2")
    grid = int(os.environ.get("BENCH_GRID", "500"))
    rings = int(os.environ.get("BENCH_RINGS", "400"))
    shutter = os.environ.get("BENCH_SHUTTER", "")
    times = [f / FPS for f in range(frames)]
    with tempfile.TemporaryDirectory(prefix="rf-animation-") as tmp:
        scene = Path(tmp) / "animated.glb"
        parts = write_scene(scene, grid, rings, frames)
        stats_path = Path(tmp) / "stats.json"
        cmd = [
            str(binary),
            "render",
            str(scene),
            "-o",
            str(Path(tmp) / "frame_{i}.exr"),
            "--spp",
            str(spp),
            "--width",
            str(size),
            "--height",
            str(size),
            "--threads",
            threads,
            "--times",
            ",".join(repr(t) for t in times),
            "--stats-json",
            str(stats_path),
        ]
        if shutter:
            cmd += ["--shutter", shutter, "--fps", str(FPS)]
        proc = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        if proc.returncode != 0:
            sys.exit(f"renderfarm-worker failed ({proc.returncode}):\n{proc.stderr}")
        stats = json.loads(stats_path.read_text())
    per_frame = stats["frames"]
    updates = np.array([f["update_s"] for f in per_frame])
    renders = np.array([f["render_s"] for f in per_frame])
    # The first frame builds the deformed meshes' BVHs; the others refit them.
    steady = slice(1, None) if len(per_frame) > 1 else slice(None)
    share = float(np.max(updates[steady] / renders[steady]))
    frames_per_hour = 3600.0 / float(np.mean(updates + renders))
    figures = {
        "benchmark": "animation",
        "size": size,
        "spp": spp,
        "frames": frames,
        "threads": threads,
        "shutter": shutter,
        **parts,
        "load_s": stats["load_s"],
        "per_frame": per_frame,
        "update_s_median": float(np.median(updates[steady])),
        "update_s_first": float(updates[0]),
        "render_s_median": float(np.median(renders)),
        "max_update_share": share,
        "frames_per_hour": frames_per_hour,
        "command": " ".join(["renderfarm-worker", "render", "animated.glb", *cmd[3:]]),
    }
    verdict = "meets" if share < TARGET_UPDATE_SHARE else "misses"
    print(
        f"{parts['static_triangles']:,} static, {parts['rigid_triangles']} rigid and "
        f"{parts['skinned_triangles']:,} skinned triangles; {frames} frames at {size}x{size}, "
        f"{spp} spp, {threads} threads" + (f", shutter {shutter} (motion blur)" if shutter else "")
    )
    print(f"load (parse + static part, once): {stats['load_s']:.3f} s")
    for f in per_frame:
        how = f"{f.get('refits', 0)} refit, {f.get('builds', 0)} built"
        print(
            f"  frame {f['index']} (t = {f['time']:.3f} s): update {f['update_s'] * 1e3:7.2f} ms "
            f"({how}), render {f['render_s']:7.2f} s"
        )
    print(
        f"scene update {figures['update_s_median'] * 1e3:.2f} ms median after the first frame "
        f"({figures['update_s_first'] * 1e3:.2f} ms for it), at most {share:.3%} of a frame's "
        f"render ({verdict} the {TARGET_UPDATE_SHARE:.0%} goal); {frames_per_hour:.0f} frames "
        f"per hour"
    )
    out = write_results("animation_blur" if shutter else "animation", figures)
    print(f"wrote {out.relative_to(ROOT)}")
    return figures


if __name__ == "__main__":
    main()
