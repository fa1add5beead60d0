"""Renders the project's Cornell box (examples/cornell-box.gltf) with Mitsuba 3, for
bench/worker_throughput.py --mitsuba. Runs inside a Python with the mitsuba package
(.venv-mitsuba: scripts/install-deps.sh --mitsuba):

    .venv-mitsuba/bin/python bench/support/mitsuba_render.py CONFIG.json

CONFIG: {"scene": the glTF path, "width", "height", "spp", "max_depth" (the farm's: bounces
after the camera's hit; Mitsuba's max_depth counts the camera's segment too, so it gets
max_depth + 1), "variant" (default "llvm_ad_rgb"), "renders" (default 3), "isa" (default
"native": Dr.Jit compiles for this CPU; "avx2": for an AVX2 CPU (LLVM's `haswell`, 8-wide
vectors), as on a CPU without AVX-512; its Embree is capped by the caller, which preloads
bench/support/embree_isa_shim.c)}.

The glTF is read here with json and numpy alone (Mitsuba reads no glTF): each mesh primitive
(float32 POSITION, uint16/uint32 indices, in the file's own .bin) becomes a Mitsuba mesh at its
node's translation (the Cornell box's meshes have no other transform), each material a
`principled` BSDF with the glTF base colour, metallic and roughness (specular 0.5 is the glTF
dielectric's F0 of 0.04) and its emission (emissiveFactor x KHR_materials_emissive_strength)
an `area` emitter; the camera the glTF's perspective camera (yfov, node translation and
rotation). The film is 32-bit RGB with a box filter, the sampler Mitsuba's `independent`, the
integrator `path`.

Prints `RESULT {"seconds": [...], "variant": ..., "samples": ...}`: the wall time of each
mi.render call after the scene is loaded. The first includes the JIT's compilation of the
kernels (LLVM), the later ones reuse them; the caller takes the later ones' median.
"""

from __future__ import annotations

import ctypes
import json
import os
import sys
import time
from pathlib import Path

import numpy as np


def quat_rotate(q, v):
    x, y, z, w = q
    u = np.array([x, y, z])
    v = np.asarray(v, float)
    return v + 2.0 * np.cross(u, np.cross(u, v) + w * v)


def read_accessor(doc, blob, index):
    acc = doc["accessors"][index]
    view = doc["bufferViews"][acc["bufferView"]]
    dtype = {5126: np.float32, 5123: np.uint16, 5125: np.uint32}[acc["componentType"]]
    width = {"SCALAR": 1, "VEC3": 3, "VEC2": 2}[acc["type"]]
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    data = np.frombuffer(blob, dtype, acc["count"] * width, start)
    return data.reshape(acc["count"], width) if width > 1 else data


def scene_dict(mi, config) -> dict:
    path = Path(config["scene"])
    doc = json.loads(path.read_text())
    blob = (path.parent / doc["buffers"][0]["uri"]).read_bytes()
    scene = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": int(config["max_depth"]) + 1},
    }
    for k, node in enumerate(doc["nodes"]):
        offset = np.array(node.get("translation", [0, 0, 0]), float)
        if "camera" in node:
            cam = doc["cameras"][node["camera"]]["perspective"]
            q = node.get("rotation", [0, 0, 0, 1])
            forward = quat_rotate(q, [0, 0, -1])
            up = quat_rotate(q, [0, 1, 0])
            scene["camera"] = {
                "type": "perspective",
                "fov_axis": "y",
                "fov": float(np.degrees(cam["yfov"])),
                "to_world": mi.ScalarTransform4f.look_at(
                    origin=offset.tolist(), target=(offset + forward).tolist(), up=up.tolist()
                ),
                "film": {
                    "type": "hdrfilm",
                    "width": int(config["width"]),
                    "height": int(config["height"]),
                    "rfilter": {"type": "box"},
                    "pixel_format": "rgb",
                },  # fmt: skip
                "sampler": {"type": "independent", "sample_count": int(config["spp"])},
            }
        if "mesh" not in node:
            continue
        for p, prim in enumerate(doc["meshes"][node["mesh"]]["primitives"]):
            positions = read_accessor(doc, blob, prim["attributes"]["POSITION"]) + offset
            faces = read_accessor(doc, blob, prim["indices"]).reshape(-1, 3).astype(np.uint32)
            material = doc["materials"][prim["material"]]
            pbr = material.get("pbrMetallicRoughness", {})
            props = mi.Properties()
            props["bsdf"] = mi.load_dict({
                "type": "principled",
                "base_color": {"type": "rgb", "value": pbr.get("baseColorFactor", [1, 1, 1])[:3]},
                "metallic": float(pbr.get("metallicFactor", 1.0)),
                "roughness": float(pbr.get("roughnessFactor", 1.0)),
                "specular": 0.5,
            })  # fmt: skip
            emissive = np.array(material.get("emissiveFactor", [0, 0, 0]), float)
            strength = (
                material.get("extensions", {})
                .get("KHR_materials_emissive_strength", {})
                .get("emissiveStrength", 1.0)
            )
            if emissive.any():
                props["emitter"] = mi.load_dict({
                    "type": "area",
                    "radiance": {"type": "rgb", "value": (emissive * strength).tolist()},
                })  # fmt: skip
            mesh = mi.Mesh(f"mesh{k}_{p}", len(positions), len(faces), props=props)
            params = mi.traverse(mesh)
            params["vertex_positions"] = mi.Float(positions.astype(np.float32).ravel())
            params["faces"] = mi.UInt32(faces.ravel())
            params.update()
            scene[f"mesh{k}_{p}"] = mesh
    return scene


def llvm_target_avx2() -> str:
    """Dr.Jit's LLVM backend set to compile for an AVX2 CPU (jit_llvm_set_target of its core
    library: `haswell`, with the host's feature flags less every AVX-512 and AMX one, so that
    the code it chooses by feature (gathers, FMA) is what an AVX2 CPU gets, and 8-wide
    vectors); returns the target it reports."""
    import drjit as dr

    x = dr.llvm.Float([1.0, 2.0]) * 2.0  # the LLVM backend initialized (it sets its target)
    dr.eval(x)
    core = ctypes.CDLL(os.path.join(os.path.dirname(dr.__file__), "libdrjit-core.so"))
    core.jit_llvm_target_cpu.restype = ctypes.c_char_p
    core.jit_llvm_target_features.restype = ctypes.c_char_p
    host = (core.jit_llvm_target_features() or b"").decode().split(",")
    features = ",".join(
        "-" + f[1:] if f.startswith(("+avx512", "+amx")) else f for f in host if f
    )  # fmt: skip
    if "+avx2" not in features.split(","):
        sys.exit(f"the host has no AVX2 for Dr.Jit to target: {features}")
    core.jit_llvm_set_target(b"haswell", features.encode(), ctypes.c_uint32(8))
    cpu = core.jit_llvm_target_cpu().decode()
    now = (core.jit_llvm_target_features() or b"").decode()
    if cpu != "haswell" or "+avx512f" in now.split(","):
        sys.exit(f"Dr.Jit kept its LLVM target {cpu!r} ({now})")
    return cpu


def main() -> None:
    config = json.loads(Path(sys.argv[1]).read_text())
    import mitsuba as mi

    variant = config.get("variant", "llvm_ad_rgb")
    mi.set_variant(variant)
    target = None
    if config.get("isa", "native") == "avx2":
        target = llvm_target_avx2()
    scene = mi.load_dict(scene_dict(mi, config))
    seconds = []
    for k in range(int(config.get("renders", 3))):
        start = time.perf_counter()
        image = mi.render(scene, spp=int(config["spp"]), seed=k)
        np.asarray(image)  # waits for the kernels (Dr.Jit evaluates lazily)
        seconds.append(time.perf_counter() - start)
    samples = int(config["width"]) * int(config["height"]) * int(config["spp"])
    mean = float(np.asarray(image).mean())
    print("RESULT " + json.dumps({"seconds": seconds, "variant": variant, "samples": samples,
                                  "mean": mean, "llvm_target": target}))  # fmt: skip


if __name__ == "__main__":
    main()
