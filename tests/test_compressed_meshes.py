"""Compressed meshes as the tools people use write them: gltfpack (meshoptimizer's packer,
Debian's gltfpack package) writes EXT_meshopt_compression, Blender's own glTF exporter writes
KHR_draco_mesh_compression. Each compressed file is rendered by the worker beside its
uncompressed twin from the same tool: the same image where the codec is lossless
(meshopt, after gltfpack's own quantization: to float rounding, as gltfpack orders triangles
differently for the codec), within the codec's quantization where it is not
(Draco's default 14-bit positions and 10-bit normals). A farm accepts and renders both, from a
.glb and from a .gltf whose meshopt target buffer has no data."""

from __future__ import annotations

import json
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest

from renderfarm.domain.scenes.pack import pack_gltf
from renderfarm.infra.images import read_exr

from .test_blender_addon import blender_python
from .tools import require_tool

ROOT = Path(__file__).resolve().parents[1]
RENDER = ["--spp", "8", "--width", "48", "--height", "40", "--threads", "1", "--seed", "5"]


def gltfpack() -> str:
    path = shutil.which("gltfpack")
    require_tool(path is not None, "gltfpack (apt: gltfpack, scripts/install-deps.sh)")
    return path


def glb_json(path: Path) -> dict:
    data = path.read_bytes()
    (length,) = struct.unpack_from("<I", data, 12)
    return json.loads(data[20 : 20 + length])


def sphere_scene(path: Path) -> Path:
    """A smooth UV sphere (positions, normals, texture coordinates) over a floor, a point
    light and a camera, as a .gltf with its .bin: every attribute gltfpack quantizes and
    compresses."""
    rings, segments = 16, 32
    theta = np.linspace(0, np.pi, rings + 1)
    phi = np.linspace(0, 2 * np.pi, segments + 1)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    normals = np.stack([np.sin(t) * np.cos(p), np.cos(t), np.sin(t) * np.sin(p)], -1)
    positions = normals + np.array([0.0, 1.0, 0.0])
    uv = np.stack([p / (2 * np.pi), t / np.pi], -1)
    idx = []
    for r in range(rings):
        for s in range(segments):
            a, b = r * (segments + 1) + s, (r + 1) * (segments + 1) + s
            idx += [a, a + 1, b, a + 1, b + 1, b]
    floor = np.array([[-3, 0, -3], [3, 0, -3], [3, 0, 3], [-3, 0, 3]], float)
    arrays = [
        positions.reshape(-1, 3).astype(np.float32),
        normals.reshape(-1, 3).astype(np.float32),
        uv.reshape(-1, 2).astype(np.float32),
        np.array(idx, np.uint32),
        floor.astype(np.float32),
        np.array([[0, 1, 0]] * 4, np.float32),
        np.array([0, 2, 1, 0, 3, 2], np.uint32),
    ]
    blob, views = b"", []
    for a in arrays:
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": a.nbytes})
        blob += a.tobytes()
    n = len(arrays[0])

    def acc(view, count, kind, ctype=5126, bounds=None):
        out = {"bufferView": view, "componentType": ctype, "count": count, "type": kind}
        if bounds is not None:
            out["min"], out["max"] = bounds
        return out

    doc = {
        "asset": {"version": "2.0"},
        "extensionsUsed": ["KHR_lights_punctual"],
        "scene": 0,
        "scenes": [{"nodes": [0, 1, 2, 3]}],
        "nodes": [
            {"mesh": 0},
            {"mesh": 1},
            {"camera": 0, "translation": [0, 1.5, 5.5], "rotation": [-0.0499, 0, 0, 0.9988]},
            {"translation": [2, 4, 3], "extensions": {"KHR_lights_punctual": {"light": 0}}},
        ],
        "cameras": [{"type": "perspective", "perspective": {"yfov": 0.7, "znear": 0.1}}],
        "extensions": {"KHR_lights_punctual": {"lights": [{"type": "point", "intensity": 200.0}]}},
        "materials": [
            {
                "pbrMetallicRoughness": {
                    "baseColorFactor": [0.8, 0.3, 0.1, 1],
                    "roughnessFactor": 0.5,
                    "metallicFactor": 0,
                }
            },
            {"pbrMetallicRoughness": {"baseColorFactor": [0.6, 0.6, 0.6, 1], "metallicFactor": 0}},
        ],  # fmt: skip
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
            {
                "primitives": [
                    {"attributes": {"POSITION": 4, "NORMAL": 5}, "indices": 6, "material": 1}
                ]
            },
        ],  # fmt: skip
        "accessors": [
            acc(0, n, "VEC3", bounds=([-1, 0, -1], [1, 2, 1])),
            acc(1, n, "VEC3"),
            acc(2, n, "VEC2"),
            acc(3, len(idx), "SCALAR", 5125),
            acc(4, 4, "VEC3", bounds=([-3, 0, -3], [3, 0, 3])),
            acc(5, 4, "VEC3"),
            acc(6, 6, "SCALAR", 5125),
        ],
        "bufferViews": views,
        "buffers": [{"byteLength": len(blob), "uri": "sphere.bin"}],
    }
    path.mkdir(parents=True, exist_ok=True)
    (path / "sphere.bin").write_bytes(blob)
    (path / "sphere.gltf").write_text(json.dumps(doc))
    return path / "sphere.gltf"


def render(worker: str, scene: Path, out: Path, integrator: str = "path") -> np.ndarray:
    proc = subprocess.run(
        [worker, "render", str(scene), "-o", str(out), "--integrator", integrator, *RENDER],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, f"{scene.name}: {proc.stderr[-2000:]}"
    channels = read_exr(str(out))
    return np.stack([channels["R"], channels["G"], channels["B"]], -1)


def pack(tool: str, src: Path, dst: Path, *flags: str) -> Path:
    proc = subprocess.run(
        [tool, "-i", str(src), "-o", str(dst), *flags], capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, proc.stderr
    return dst


def test_meshopt_files_render_as_their_uncompressed_twins(worker_binary, tmp_path):
    tool = gltfpack()
    src = sphere_scene(tmp_path / "src")
    quantized = pack(tool, src, tmp_path / "q.glb")  # KHR_mesh_quantization, no compression
    compressed = pack(tool, src, tmp_path / "c.glb", "-c")  # the same data, meshopt-coded
    filtered = pack(tool, src, tmp_path / "cc.glb", "-cc")  # + octahedral normals filter
    lossless = pack(tool, src, tmp_path / "n.glb", "-c", "-noq")  # float attributes, coded
    for path, filters in ((compressed, {None}), (filtered, {None, "OCTAHEDRAL"})):
        doc = glb_json(path)
        assert "EXT_meshopt_compression" in doc["extensionsRequired"]
        used = {
            v["extensions"]["EXT_meshopt_compression"].get("filter")
            for v in doc["bufferViews"]
            if "extensions" in v
        }
        assert used == filters, (path.name, used)

    base = render(worker_binary, quantized, tmp_path / "q.exr")
    assert base.mean() > 0.01
    # The codec is lossless on what gltfpack quantized: the same image, to the float rounding
    # of the triangles gltfpack orders differently for the codec (a misdecoded vertex or index
    # would move whole pixels).
    coded = render(worker_binary, compressed, tmp_path / "c.exr")
    assert np.abs(coded - base).max() <= 1e-5 * max(base.max(), 1.0)
    # Float attributes coded losslessly: the original scene's image (to float rounding of
    # gltfpack's reordered triangles).
    original = render(worker_binary, src, tmp_path / "o.exr", "direct")
    coded = render(worker_binary, lossless, tmp_path / "n.exr", "direct")
    assert np.abs(coded - original).max() <= 1e-5 * max(original.max(), 1.0)
    # Octahedral normals of 8-bit coordinates, against the exact normals: shading within the
    # normals' angular error (< 2 degrees) on average.
    octahedral = render(worker_binary, filtered, tmp_path / "cc.exr", "direct")
    assert abs(octahedral.mean() / original.mean() - 1) < 0.01
    assert np.abs(octahedral - original).mean() < 0.02 * original.mean()


def test_draco_from_blenders_exporter_renders_as_the_plain_export(worker_binary, tmp_path):
    python = blender_python()
    proc = subprocess.run(
        [python, str(ROOT / "tests" / "blender_export.py"), str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0 and "EXPORTED" in proc.stdout, proc.stderr[-3000:]
    plain, draco = tmp_path / "plain.glb", tmp_path / "draco.glb"
    doc = glb_json(draco)
    assert "KHR_draco_mesh_compression" in doc["extensionsRequired"]
    assert all(
        "KHR_draco_mesh_compression" in p.get("extensions", {})
        for m in doc["meshes"]
        for p in m["primitives"]
    )
    assert draco.stat().st_size < plain.stat().st_size
    a = render(worker_binary, plain, tmp_path / "plain.exr", "direct")
    b = render(worker_binary, draco, tmp_path / "draco.exr", "direct")
    assert a.mean() > 0.01
    # Draco's quantization moves vertices by under 1e-4 of the scene's size and turns normals
    # by a fraction of a degree: the same picture but at a few silhouette pixels.
    assert abs(b.mean() / a.mean() - 1) < 0.005
    close = np.abs(b - a) <= 0.02 * a.max()
    assert close.mean() > 0.97, close.mean()


def test_a_farm_renders_compressed_uploads(client, tmp_path):
    tool = gltfpack()
    src = sphere_scene(tmp_path / "src")
    glb = pack(tool, src, tmp_path / "c.glb", "-cc")
    # A .gltf whose decoded buffer has no data (no uri): packing keeps it a buffer of its own.
    gltf = pack(tool, src, tmp_path / "c.gltf", "-c")
    target = [b for b in json.loads(gltf.read_text())["buffers"] if "uri" not in b]
    assert target and target[0]["extensions"]["EXT_meshopt_compression"]["fallback"] is True
    packed = glb_json_bytes(pack_gltf(gltf))
    assert [("uri" in b, "extensions" in b) for b in packed["buffers"]] == [
        (False, False),
        (False, True),
    ]
    settings = {"width": 32, "height": 32, "tile_size": 16, "max_spp": 4, "seed": 1}
    for scene in (glb, gltf):
        job = client.submit(scene, settings=settings, name=f"compressed {scene.suffix}")
        done = client.wait(job["id"], poll_s=0.2, timeout_s=120)
        assert done["state"] == "completed", done
        rgb = read_exr_bytes(client.image(job["id"], "exr"), tmp_path / f"{scene.suffix}.exr")
        assert rgb.mean() > 0.01


def glb_json_bytes(data: bytes) -> dict:
    (length,) = struct.unpack_from("<I", data, 12)
    return json.loads(data[20 : 20 + length])


def read_exr_bytes(data: bytes, path: Path) -> np.ndarray:
    path.write_bytes(data)
    channels = read_exr(str(path))
    return np.stack([channels["R"], channels["G"], channels["B"]], -1)


@pytest.mark.parametrize("mode", ["ATTRIBUTES", "TRIANGLES"])
def test_a_corrupt_meshopt_stream_is_refused_naming_its_buffer_view(client, tmp_path, mode):
    tool = gltfpack()
    glb = pack(tool, sphere_scene(tmp_path / "src"), tmp_path / "c.glb", "-c")
    data = bytearray(glb.read_bytes())
    doc = glb_json(glb)
    view = next(
        i
        for i, v in enumerate(doc["bufferViews"])
        if v.get("extensions", {}).get("EXT_meshopt_compression", {}).get("mode") == mode
    )
    ext = doc["bufferViews"][view]["extensions"]["EXT_meshopt_compression"]
    (json_length,) = struct.unpack_from("<I", data, 12)
    bin_start = 20 + json_length + 8  # the BIN chunk's data (buffer 0)
    start = bin_start + ext.get("byteOffset", 0)
    data[start : start + ext["byteLength"]] = b"\xff" * ext["byteLength"]
    bad = tmp_path / "bad.glb"
    bad.write_bytes(bytes(data))
    r = client.http.post(
        "/api/v1/jobs",
        data={"settings": "{}"},
        files={"scene": ("bad.glb", bad.read_bytes(), "model/gltf-binary")},
    )
    assert r.status_code == 400, r.text
    body = r.json()
    assert body["field"] == f"scene.bufferViews[{view}].extensions.EXT_meshopt_compression", body
    assert "does not decode" in body["detail"]
