"""Worker memory and load time for a scene of millions of triangles.

Writes a .glb of a wavy indexed grid (NORMAL, TEXCOORD_0, uint32 indices: the layout exporters
produce) under an emissive quad to a temporary directory, renders it with
`renderfarm-worker render` at a tiny size with each BVH layout (`--bvh fast` and
`--bvh compact`), and reports per layout: the scene memory the worker prints (its triangle
meshes, light tables and Embree's BVH), bytes per triangle, the worker process's peak RSS
(wait4's figure for that child: it includes the shared libraries, about 125 MB, and the glTF
parser's copy of the file while loading) and the wall time of the whole run (load, BVH build
and a 64x64, 1 spp render). Writes bench/results/scene_memory.json.

Environment: RENDERFARM_WORKER (binary, default build/worker/renderfarm-worker),
BENCH_GRID (quads per side, default 1415: 4.0M triangles).
"""

from __future__ import annotations

import json
import os
import re
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from support.results import write_results  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent


def grid_glb(n: int, path: Path) -> int:
    """An n x n quad grid (2 n^2 triangles) in [-1, 1]^2 with a gentle wave, and a lamp above;
    returns the triangle count."""
    xs = np.linspace(-1.0, 1.0, n + 1, dtype=np.float32)
    x, z = np.meshgrid(xs, xs)
    y = (0.05 * np.sin(8 * x) * np.cos(8 * z)).astype(np.float32)
    pos = np.stack([x, y, z], -1).reshape(-1, 3)
    nrm = np.stack([-0.4 * np.cos(8 * x) * np.cos(8 * z), np.ones_like(x),
                    0.4 * np.sin(8 * x) * np.sin(8 * z)], -1).reshape(-1, 3)  # fmt: skip
    nrm = (nrm / np.linalg.norm(nrm, axis=1, keepdims=True)).astype(np.float32)
    uv = np.stack([(x + 1) / 2, (z + 1) / 2], -1).reshape(-1, 2).astype(np.float32)
    i = np.arange(n, dtype=np.uint32)
    a = (i[:, None] * (n + 1) + i[None, :]).ravel()
    b, c = a + 1, a + n + 1
    idx = np.stack([a, c, b, b, c, c + 1], -1).reshape(-1).astype(np.uint32)
    lamp = np.array([[-0.3, 1, -0.3], [0.3, 1, -0.3], [-0.3, 1, 0.3], [0.3, 1, 0.3]], np.float32)
    lamp_idx = np.array([0, 2, 1, 1, 2, 3], np.uint32)  # faces -y, down onto the grid
    blobs = [pos, nrm, uv, idx, lamp, lamp_idx]
    views, offset = [], 0
    for blob in blobs:
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": blob.nbytes})
        offset += blob.nbytes
    binary = b"".join(blob.tobytes() for blob in blobs)

    def accessor(view: int, count: int, kind: str, ctype: int = 5126, **extra) -> dict:
        return {"bufferView": view, "componentType": ctype, "count": count, "type": kind, **extra}

    doc = {
        "asset": {"version": "2.0", "generator": "bench/scene_memory.py"},
        "extensionsUsed": ["KHR_materials_emissive_strength"],
        "scene": 0,
        "scenes": [{"nodes": [0, 1, 2]}],
        "nodes": [
            {"mesh": 0},
            {"mesh": 1},
            {"camera": 0, "translation": [0, 1.5, 2.5], "rotation": [-0.2588, 0, 0, 0.9659]},
        ],
        "cameras": [{"type": "perspective", "perspective": {"yfov": 0.8, "znear": 0.01}}],
        "materials": [
            {
                "pbrMetallicRoughness": {
                    "baseColorFactor": [0.7, 0.7, 0.7, 1],
                    "metallicFactor": 0,
                    "roughnessFactor": 0.5,
                }
            },
            {
                "emissiveFactor": [1, 1, 1],
                "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": 20}},
            },
        ],
        "meshes": [
            {
                "primitives": [
                    {
                        "attributes": {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2},
                        "indices": 3,
                        "material": 0,
                    }
                ]
            },
            {"primitives": [{"attributes": {"POSITION": 4}, "indices": 5, "material": 1}]},
        ],
        "accessors": [
            accessor(0, len(pos), "VEC3", min=pos.min(0).tolist(), max=pos.max(0).tolist()),
            accessor(1, len(nrm), "VEC3"),
            accessor(2, len(uv), "VEC2"),
            accessor(3, len(idx), "SCALAR", 5125),
            accessor(4, 4, "VEC3", min=lamp.min(0).tolist(), max=lamp.max(0).tolist()),
            accessor(5, 6, "SCALAR", 5125),
        ],
        "bufferViews": views,
        "buffers": [{"byteLength": len(binary)}],
    }
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    binary += b"\0" * (-len(binary) % 4)
    with open(path, "wb") as f:
        f.write(struct.pack("<III", 0x46546C67, 2, 12 + 8 + len(text) + 8 + len(binary)))
        f.write(struct.pack("<II", len(text), 0x4E4F534A) + text)
        f.write(struct.pack("<II", len(binary), 0x004E4942) + binary)
    return 2 * n * n + 2


def run_worker(cmd: list[str], log: Path) -> tuple[int, str, int, float]:
    """Runs cmd with stderr to log; returns its exit status, stderr, peak RSS in bytes (this
    child's own, from wait4) and wall seconds."""
    t0 = time.monotonic()
    with open(log, "w") as err:
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err)
        _, status, usage = os.wait4(proc.pid, 0)
    seconds = time.monotonic() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)  # reaped here, not by Popen
    return proc.returncode, log.read_text(), usage.ru_maxrss * 1024, seconds  # KiB on Linux


def main() -> dict:
    binary = Path(os.environ.get("RENDERFARM_WORKER", ROOT / "build/worker/renderfarm-worker"))
    if not binary.exists():
        sys.exit(f"{binary} not found: build the worker first (make worker)")
    grid = int(os.environ.get("BENCH_GRID", "1415"))
    figures = {"benchmark": "scene_memory", "grid": grid, "layouts": {}}
    with tempfile.TemporaryDirectory(prefix="rf-scene-memory-") as tmp:
        scene = Path(tmp) / "grid.glb"
        triangles = grid_glb(grid, scene)
        file_bytes = scene.stat().st_size
        figures["triangles"] = triangles
        figures["file_bytes"] = file_bytes
        for bvh in ("fast", "compact"):
            cmd = [str(binary), "render", str(scene), "-o", str(Path(tmp) / "out.exr"),
                   "--spp", "1", "--width", "64", "--height", "64", "--threads", "2",
                   "--bvh", bvh]  # fmt: skip
            code, stderr, peak_rss, seconds = run_worker(cmd, Path(tmp) / "stderr.txt")
            if code != 0:
                sys.exit(f"renderfarm-worker failed ({code}):\n{stderr}")
            m = re.search(r": (\d+) triangles \(([\d.]+) (kB|MB|GB) in memory\)", stderr)
            if not m:
                sys.exit(f"no scene line in the worker's output:\n{stderr}")
            if int(m.group(1)) != triangles:
                sys.exit(f"the worker loaded {m.group(1)} triangles, the file has {triangles}")
            scene_bytes = float(m.group(2)) * {"kB": 1e3, "MB": 1e6, "GB": 1e9}[m.group(3)]
            figures["layouts"][bvh] = {
                "scene_memory_bytes": scene_bytes,
                "bytes_per_triangle": scene_bytes / triangles,
                "peak_rss_bytes": peak_rss,
                "seconds_load_build_render": seconds,
                "command": " ".join(["renderfarm-worker", "render", "grid.glb", *cmd[3:]]),
            }
            print(
                f"--bvh {bvh:7}: {triangles:,} triangles ({file_bytes / 1e6:.0f} MB .glb): "
                f"scene {scene_bytes / 1e6:.0f} MB in memory ({scene_bytes / triangles:.0f} "
                f"bytes per triangle), peak RSS {peak_rss / 1e6:.0f} MB, load + build + render "
                f"{seconds:.2f} s"
            )
    out = write_results("scene_memory", figures)
    print(f"wrote {out.relative_to(ROOT)}")
    return figures


if __name__ == "__main__":
    main()
