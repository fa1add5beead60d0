"""Cycles parity: the farm's worker against Blender's Cycles on the same glTF scene.

For one scene (a glTF/GLB file, or a parity scene of bench/support/parity_scenes.py by name) or
the whole suite (--suite):
1. Cycles (bpy in .venv-blender) imports the scene with Blender's glTF importer and renders it
   with settings matched to the farm's path tracer (bench/support/cycles_render.py: CPU, 1-pixel
   box filter, max_depth - 1 bounces of every kind, no clamping, no glossy filter, light
   threshold 0, no shadow-terminator offsets, caustics on, black world, no adaptive sampling,
   no denoising): --renders independent renders at --spp (seeds 1..K) and one reference at
   --reference-spp.
2. The standalone worker (build/worker/renderfarm-worker render) renders it --renders times at
   --spp (seeds 1..K), then --renders times at the spp that takes as long as Cycles' render
   (equal time).
3. Per region (the image, a --grid x --grid grid of blocks, any --region rectangles) and per
   channel (R, G, B): the mean ratio worker / Cycles with its standard error, the MSE of one
   render of each side against the reference, and the efficiency 1 / (MSE x seconds) of the
   worker over Cycles' at equal spp and at equal time (docs/parity.md has the statistics).
An animated scene is compared at chosen frames (--frame F, repeatable or F,G,...; an animated
parity scene without --frame: its ANIMATED frames): the worker renders `--time F / fps` (the
farm's time of frame F, domain/frames.py frame_time), Cycles imports the scene with the same
frame rate and renders frame F (scene.frame_set); each frame is compared as a scene of its own,
NAME_fF. For every scene the harness also splits the error at the reference's edges
(silhouettes, shadow edges) from the rest ("edges" in the JSON): a pose that differs shows as
the worker's error on the edges above Cycles' (the noise), the rest alike.
Writes OUT/NAME.json (every figure), OUT/NAME.png (worker | Cycles | ratio heat map) and, for
more than one scene, OUT/parity.json (the suite also bench/results/cycles_parity.json); prints a
table. Without a scene it runs the suite. --realistic runs the realistic suite instead
(bench/support/parity_scenes.py REALISTIC: scenes where indirect light, glossy reflections and
caustics make the noise, as in studios' work; #38) at that issue's settings unless given, and
writes bench/results/cycles_realistic.json.

    .venv/bin/python bench/cycles_parity.py rough_dielectric [--spp 64] [--reference-spp 4096]
    .venv/bin/python bench/cycles_parity.py --suite --out out/parity
    .venv/bin/python bench/cycles_parity.py --realistic --out out/realistic
    .venv/bin/python bench/cycles_parity.py my-scene.glb --region 10,10,40,30
    .venv/bin/python bench/cycles_parity.py animated_shot --frame 1,24,48
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from support.parity_scenes import ANIMATED, REALISTIC, SCENES
from support.results import write_results

from renderfarm.domain.scenes.glb import build_glb, parse_json, split_glb
from renderfarm.infra.images import read_exr, srgb_encode

ROOT = Path(__file__).resolve().parents[1]
SUPPORT = Path(__file__).resolve().parent / "support"
CHANNELS = ("R", "G", "B")
LUMA = np.array([0.2126, 0.7152, 0.0722])
# The heat map spans ratios 1/2 (blue) to 2 (red); pixels darker than this on both sides
# (relative to the image's mean) carry no ratio and are drawn black.
HEAT_STOPS = 1.0
HEAT_DARK = 1e-3
# A pixel is on an edge of the reference (a silhouette, a shadow's edge) where its luminance
# differs from one of its 8 neighbours' by more than this fraction of the image's mean.
EDGE_CONTRAST = 0.25


def blender_python() -> Path:
    explicit = os.environ.get("RENDERFARM_BLENDER_PYTHON")
    path = Path(explicit) if explicit else ROOT / ".venv-blender" / "bin" / "python"
    if not path.exists():
        sys.exit(f"no Blender Python at {path} (scripts/install-deps.sh --blender, or set "
                 "RENDERFARM_BLENDER_PYTHON)")  # fmt: skip
    return path


def worker_binary() -> Path:
    explicit = os.environ.get("RENDERFARM_WORKER_BINARY")
    path = Path(explicit) if explicit else ROOT / "build" / "worker" / "renderfarm-worker"
    if not path.exists():
        sys.exit(f"no worker binary at {path} (make worker, or set RENDERFARM_WORKER_BINARY)")
    return path


def run_blender(script: Path, args: list[str], out: Path, what: str) -> dict:
    """Run a script in Blender's Python; the JSON of its `RESULT {...}` line."""
    env = {**os.environ, "BLENDER_USER_RESOURCES": str(out / "blender-user")}
    proc = subprocess.run([str(blender_python()), str(script), *args], env=env,
                          capture_output=True, text=True)  # fmt: skip
    for line in proc.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[len("RESULT ") :])
    tail = "\n".join((proc.stdout + proc.stderr).splitlines()[-30:])
    sys.exit(f"{what} failed (exit {proc.returncode}):\n{tail}")


def generate_scenes(names: list[str], out: Path) -> dict[str, dict]:
    """{name: {"scene": glb path, "environment": map path or None}} of the parity scenes."""
    return run_blender(SUPPORT / "parity_scenes.py", [str(out / "scenes"), *names], out,
                       "Blender exporting the parity scenes")  # fmt: skip


def rgb(path: Path) -> np.ndarray:
    ch = read_exr(str(path))
    return np.stack([ch[c] for c in CHANNELS], axis=-1).astype(np.float64)


def render_cycles(
    scene: Path,
    env: dict | None,
    name: str,
    args,
    out: Path,
    frame: dict | None = None,
    extra: dict | None = None,
) -> dict:
    """K renders at --spp, then the reference; their images and seconds. frame: None, or
    {"frame": F, "fps": rate} of an animated scene. extra: further keys of cycles_render.py's
    CONFIG (bench/usd_parity.py: the USD importer, the camera, the imported world)."""
    scratch = out / "renders" / name
    scratch.mkdir(parents=True, exist_ok=True)
    renders = [{"spp": args.spp, "seed": k + 1, "path": str(scratch / f"cycles-{k + 1}.exr")}
               for k in range(args.renders)]  # fmt: skip
    # The reference's seed is none of the K renders', so its noise is independent of theirs.
    ref = {"spp": args.reference_spp, "seed": 1000, "path": str(scratch / "cycles-reference.exr")}
    config = {"scene": str(scene), "width": args.width, "height": args.height,
              "max_depth": args.max_depth, "threads": args.threads,
              "renders": [*renders, ref], "environment": env,
              "microfacet": args.cycles_microfacet, "textures": args.cycles_textures,
              "volume": args.cycles_volume,
              "anisotropy": args.cycles_anisotropy,
              "frame": frame and frame["frame"], "fps": frame and frame["fps"],
              **(extra or {})}  # fmt: skip
    config_path = scratch / "cycles.json"
    config_path.write_text(json.dumps(config))
    result = run_blender(SUPPORT / "cycles_render.py", [str(config_path)], out,
                         f"Cycles rendering {scene}")  # fmt: skip
    return {
        "images": [rgb(Path(r["path"])) for r in renders],
        "seconds": result["seconds"][:-1],
        "reference": rgb(Path(ref["path"])),
        "reference_seconds": result["seconds"][-1],
        "keys": result.get("keys"),
        "lights": result.get("lights"),
    }


WORKER_RATE = re.compile(r"in ([0-9.]+) s: ([0-9.]+) samples/s")


def render_worker(
    scene: Path,
    env: dict | None,
    name: str,
    spp: int,
    args,
    out: Path,
    tag: str,
    frame: dict | None = None,
    extra_args: tuple[str, ...] = (),
) -> dict:
    """K renders at spp with the standalone worker; their images and wall-clock seconds (the
    process: scene load, BVH build, sampling, writing the EXR). frame: None, or {"time": t}
    of an animated scene (its glTF animations at t seconds). extra_args: further flags of
    `render` (a USD camera's --aperture-radius and --focus-distance)."""
    scratch = out / "renders" / name
    scratch.mkdir(parents=True, exist_ok=True)
    images, seconds, sampling, rates = [], [], [], []
    for k in range(args.renders):
        path = scratch / f"worker-{tag}-{k + 1}.exr"
        cmd = [str(worker_binary()), "render", str(scene), "-o", str(path), "--spp", str(spp),
               "--width", str(args.width), "--height", str(args.height),
               "--threads", str(args.threads), "--seed", str(k + 1),
               "--max-depth", str(args.max_depth)]  # fmt: skip
        if env:
            cmd += ["--environment", env["path"], "--environment-intensity",
                    repr(env["intensity"]), "--environment-rotation-deg",
                    repr(env["rotation_deg"])]  # fmt: skip
        if frame is not None:
            cmd += ["--time", repr(frame["time"])]
        if getattr(args, "guiding", False):
            cmd += ["--guiding", "on"]
        cmd += list(extra_args)
        start = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True)
        seconds.append(time.perf_counter() - start)
        if proc.returncode != 0:
            sys.exit(f"the worker failed on {scene} (exit {proc.returncode}):\n{proc.stderr}")
        match = WORKER_RATE.search(proc.stdout + proc.stderr)
        if match:
            sampling.append(float(match.group(1)))
            rates.append(float(match.group(2)))
        images.append(rgb(path))
    return {"images": images, "seconds": seconds, "sampling_seconds": sampling,
            "samples_per_s": rates, "spp": spp}  # fmt: skip


def regions(width: int, height: int, grid: int, rects: list[tuple[int, int, int, int]]):
    """(name, (x0, y0, x1, y1)) of the whole image, the grid's blocks and the given rectangles;
    pixel rows from the top, x1 and y1 exclusive."""
    out = [("image", (0, 0, width, height))]
    if grid > 1:
        xs = np.linspace(0, width, grid + 1).round().astype(int)
        ys = np.linspace(0, height, grid + 1).round().astype(int)
        for r in range(grid):
            for c in range(grid):
                out.append((f"r{r}c{c}", (int(xs[c]), int(ys[r]), int(xs[c + 1]), int(ys[r + 1]))))
    for i, rect in enumerate(rects):
        out.append((f"rect{i}", rect))
    return out


def pixel_variance(images) -> np.ndarray:
    """Per pixel (and channel): the unbiased variance of one render across the K renders."""
    return np.stack(images).var(axis=0, ddof=1)


def region_stats(images: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per channel: the mean of the region over the K renders, its standard error (pixels
    independent: the per-pixel variances summed over n^2), and the variance of one render (the
    per-pixel variance across the renders, averaged over the region's pixels). Unlike the MSE
    against Cycles' reference the variance leaves out the bias a model difference between the
    renderers adds (docs/parity.md), which no amount of sampling removes: 1 / (variance x
    seconds) is the efficiency of the estimator itself. Needs K >= 2."""
    stack = np.stack(images)  # K x h x w x 3
    k = stack.shape[0]
    n = stack.shape[1] * stack.shape[2]
    var = pixel_variance(stack).mean(axis=(0, 1))
    return stack.mean(axis=(0, 1, 2)), np.sqrt(var / (k * n)), var


def mse(images: list[np.ndarray], reference: np.ndarray) -> np.ndarray:
    """Per channel: the mean squared error of one render against the reference (averaged over
    the K renders and the region's pixels)."""
    return np.mean([((im - reference) ** 2).mean(axis=(0, 1)) for im in images], axis=0)


def number(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def edge_mask(reference: np.ndarray) -> np.ndarray:
    """The pixels on an edge of the reference: its luminance differs from one of its 8
    neighbours' by more than EDGE_CONTRAST x the image's mean luminance."""
    y = reference @ LUMA
    h, w = y.shape
    pad = np.pad(y, 1, mode="edge")
    neighbours = np.stack([pad[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w]
                           for dy in (-1, 0, 1) for dx in (-1, 0, 1)])  # fmt: skip
    return np.abs(neighbours - y).max(axis=0) > EDGE_CONTRAST * max(float(y.mean()), 1e-12)


def ratio_or_none(a: float, b: float) -> float | None:
    return number(a / b) if b else None


def edges(cyc: dict, wrk: dict, wrk_t: dict) -> dict:
    """The luminance error against the reference split at the reference's edges: per side, the
    MSE of one render on the edge pixels and off them, and the share of its squared error on
    the edges. Where the two renderers see the same scene, the worker's edge MSE is Cycles'
    (both noise); where a pose or the camera differs, the worker's excess is on the edges."""
    ref = cyc["reference"] @ LUMA
    mask = edge_mask(cyc["reference"])

    def split(images):
        err = np.mean([((im @ LUMA - ref) ** 2) for im in images], axis=0)
        on = float(err[mask].mean()) if mask.any() else 0.0
        off = float(err[~mask].mean()) if (~mask).any() else 0.0
        return {"mse_edges": on, "mse_elsewhere": off,
                "edge_share": float(err[mask].sum() / max(err.sum(), 1e-300))}  # fmt: skip

    w, c = split(wrk["images"]), split(cyc["images"])
    return {
        "edge_contrast": EDGE_CONTRAST,
        "edge_fraction": float(mask.mean()),
        "worker": w,
        "cycles": c,
        "worker_equal_time": split(wrk_t["images"]),
        "worker_over_cycles_edges": ratio_or_none(w["mse_edges"], c["mse_edges"]),
        "worker_over_cycles_elsewhere": ratio_or_none(w["mse_elsewhere"], c["mse_elsewhere"]),
    }  # fmt: skip


def analyse(cyc: dict, wrk: dict, wrk_t: dict, args, rects) -> dict:
    t_c = float(np.mean(cyc["seconds"]))
    t_w = float(np.mean(wrk["seconds"]))
    t_wt = float(np.mean(wrk_t["seconds"]))
    rows = []
    # The reference's own noise adds to both sides' MSE: estimated from Cycles' K renders,
    # scaled by spp / reference_spp.
    ref_var = pixel_variance(cyc["images"]) * args.spp / args.reference_spp
    for name, (x0, y0, x1, y1) in regions(args.width, args.height, args.grid, rects):

        def crop(ims, x0=x0, y0=y0, x1=x1, y1=y1):
            return [im[y0:y1, x0:x1] for im in ims]

        w_mean, w_se, var_w = region_stats(crop(wrk["images"]))
        c_mean, c_se, var_c = region_stats(crop(cyc["images"]))
        var_wt = region_stats(crop(wrk_t["images"]))[2]
        ref = cyc["reference"][y0:y1, x0:x1]
        mse_w = mse(crop(wrk["images"]), ref)
        mse_c = mse(crop(cyc["images"]), ref)
        mse_wt = mse(crop(wrk_t["images"]), ref)
        noise_ref = ref_var[y0:y1, x0:x1].mean(axis=(0, 1))
        for i, ch in enumerate(CHANNELS):
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = w_mean[i] / c_mean[i]
                # (P/C) sqrt((SE_P/P)^2 + (SE_C/C)^2), written to stay defined at P = 0.
                se = math.hypot(w_se[i] / c_mean[i], w_mean[i] * c_se[i] / c_mean[i] ** 2)
                eff_w, eff_c = 1.0 / (mse_w[i] * t_w), 1.0 / (mse_c[i] * t_c)
                eff_wt = 1.0 / (mse_wt[i] * t_wt)
                # The same by the variance of one render (the estimator's own efficiency).
                veff_w, veff_c = 1.0 / (var_w[i] * t_w), 1.0 / (var_c[i] * t_c)
                veff_wt = 1.0 / (var_wt[i] * t_wt)
                rows.append({
                    "region": name, "rect": [x0, y0, x1, y1], "channel": ch,
                    "worker_mean": number(w_mean[i]), "worker_se": number(w_se[i]),
                    "cycles_mean": number(c_mean[i]), "cycles_se": number(c_se[i]),
                    "ratio": number(ratio), "ratio_se": number(se),
                    "reference_mean": number(ref[..., i].mean()),
                    "worker_mse": number(mse_w[i]), "cycles_mse": number(mse_c[i]),
                    "worker_mse_equal_time": number(mse_wt[i]),
                    "reference_noise_variance": number(noise_ref[i]),
                    "worker_efficiency": number(eff_w), "cycles_efficiency": number(eff_c),
                    "worker_efficiency_equal_time": number(eff_wt),
                    "efficiency_ratio_equal_spp": number(eff_w / eff_c),
                    "efficiency_ratio_equal_time": number(eff_wt / eff_c),
                    "worker_variance": number(var_w[i]), "cycles_variance": number(var_c[i]),
                    "worker_variance_equal_time": number(var_wt[i]),
                    "variance_efficiency_ratio_equal_spp": number(veff_w / veff_c),
                    "variance_efficiency_ratio_equal_time": number(veff_wt / veff_c),
                })  # fmt: skip
    return {
        "cycles_seconds": cyc["seconds"],
        "cycles_reference_seconds": cyc["reference_seconds"],
        "worker_seconds": wrk["seconds"],
        "worker_sampling_seconds": wrk["sampling_seconds"],
        "worker_samples_per_s": wrk["samples_per_s"],
        "equal_time_worker_spp": wrk_t["spp"],
        "equal_time_worker_seconds": wrk_t["seconds"],
        "edges": edges(cyc, wrk, wrk_t),
        "rows": rows,
    }


def heat(ratio_image: np.ndarray) -> np.ndarray:
    """log2 ratio in [-HEAT_STOPS, HEAT_STOPS] as blue (worker darker), white (equal), red
    (worker brighter); NaN (both dark) black."""
    t = np.clip(np.nan_to_num(ratio_image, nan=0.0) / HEAT_STOPS, -1.0, 1.0)
    up, down = np.clip(t, 0, 1), np.clip(-t, 0, 1)
    out = np.stack([1.0 - down, 1.0 - up - down, 1.0 - up], axis=-1)
    out[np.isnan(ratio_image)] = 0.0
    return out


def write_png(path: Path, worker: np.ndarray, cycles: np.ndarray) -> None:
    import OpenImageIO as oiio

    yw, yc = worker @ LUMA, cycles @ LUMA
    dark = HEAT_DARK * max(float(yc.mean()), 1e-12)
    with np.errstate(divide="ignore", invalid="ignore"):
        log_ratio = np.log2(np.maximum(yw, 1e-12) / np.maximum(yc, 1e-12))
    log_ratio[(yw < dark) & (yc < dark)] = np.nan
    gap = np.ones((worker.shape[0], 2, 3))
    panel = np.concatenate(
        [srgb_encode(worker), gap, srgb_encode(cycles), gap, heat(log_ratio)], axis=1
    )
    pixels = (np.clip(panel, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), oiio.ImageSpec(pixels.shape[1], pixels.shape[0], 3, oiio.UINT8))
    out.write_image(pixels)
    out.close()


def equal_time_spp(spp: int, cycles_s: float, wrk: dict) -> int:
    """The spp at which one worker render takes as long as one Cycles render at spp: the
    worker's seconds split into a fixed cost (process start, scene load, BVH build: its wall
    time less the sampling time it prints) and a cost per sample."""
    wall = float(np.mean(wrk["seconds"]))
    sampling = float(np.mean(wrk["sampling_seconds"])) if wrk["sampling_seconds"] else wall
    fixed = max(0.0, wall - sampling)
    return max(1, round(spp * max(cycles_s - fixed, 0.0) / max(sampling, 1e-9)))


def without_dielectric_specular(scene: Path, out: Path) -> tuple[Path, list[str]]:
    """A copy of the GLB scene in which every opaque dielectric (metallicFactor 0, no
    KHR_materials_transmission) has KHR_materials_specular's specularFactor 0, so that its
    BRDF is the spec's Lambert lobe alone in both renderers (Blender's importer makes that a
    Principled BSDF with Specular IOR Level 0). Metals, glass, coats and sheen are unchanged.
    What the copy leaves of a difference is not the coupling of diffuse and specular
    reflection, which is a model difference (docs/parity.md). Returns the copy and the names of
    the materials changed."""
    json_chunk, blob = split_glb(scene.read_bytes(), scene.name)
    document = parse_json(json_chunk, scene.name)
    changed = []
    for i, material in enumerate(document.get("materials", [])):
        pbr = material.get("pbrMetallicRoughness", {})
        transmission = material.get("extensions", {}).get("KHR_materials_transmission", {})
        if pbr.get("metallicFactor", 1.0) != 0 or transmission.get("transmissionFactor", 0) > 0:
            continue
        material.setdefault("extensions", {})["KHR_materials_specular"] = {"specularFactor": 0.0}
        changed.append(material.get("name", f"materials[{i}]"))
    if changed:
        used = document.setdefault("extensionsUsed", [])
        if "KHR_materials_specular" not in used:
            used.append("KHR_materials_specular")
    copy = out / "scenes" / f"{scene.stem}-lambert.glb"
    copy.parent.mkdir(parents=True, exist_ok=True)
    copy.write_bytes(build_glb(document, blob or b""))
    return copy, changed


# --coverage's flat colours, one per material in the file's order (then repeated).
COVERAGE_COLOURS = ((0.25, 0.25, 0.25), (1.0, 0.1, 0.1), (0.1, 1.0, 0.1), (0.1, 0.1, 1.0),
                    (1.0, 1.0, 0.1), (0.1, 1.0, 1.0), (1.0, 0.1, 1.0), (1.0, 1.0, 1.0))  # fmt: skip


def coverage_copy(scene: Path, out: Path) -> Path:
    """A copy of the GLB scene in which every material only emits a flat colour of its own
    (COVERAGE_COLOURS; base colour black, no texture, specularFactor 0, no transmission,
    coat or sheen, emissive strength 1) and no punctual light is left: each pixel is the
    average colour of what the camera sees through it, in both renderers the same function of
    the geometry alone. What differs in this copy is a pose, the camera or the pixel
    sampling, not shading."""
    json_chunk, blob = split_glb(scene.read_bytes(), scene.name)
    document = parse_json(json_chunk, scene.name)
    for i, material in enumerate(document.get("materials", [])):
        colour = COVERAGE_COLOURS[i % len(COVERAGE_COLOURS)]
        material.clear()
        material.update({
            "name": f"coverage{i}", "doubleSided": True, "emissiveFactor": list(colour),
            "pbrMetallicRoughness": {"baseColorFactor": [0.0, 0.0, 0.0, 1.0],
                                     "metallicFactor": 0.0, "roughnessFactor": 1.0},
            "extensions": {"KHR_materials_specular": {"specularFactor": 0.0}},
        })  # fmt: skip
    for node in document.get("nodes", []):
        node.get("extensions", {}).pop("KHR_lights_punctual", None)
    document.get("extensions", {}).pop("KHR_lights_punctual", None)
    used = [e for e in document.get("extensionsUsed", []) if e != "KHR_lights_punctual"]
    document["extensionsUsed"] = sorted({*used, "KHR_materials_specular"})
    if "extensionsRequired" in document:
        document["extensionsRequired"] = [e for e in document["extensionsRequired"]
                                          if e in document["extensionsUsed"]]  # fmt: skip
    copy = out / "scenes" / f"{scene.stem}-coverage.glb"
    copy.parent.mkdir(parents=True, exist_ok=True)
    copy.write_bytes(build_glb(document, blob or b""))
    return copy


def run_scene(
    name: str, scene: Path, env: dict | None, args, rects, out: Path, frame: dict | None = None
) -> dict:
    """One scene compared, or one frame of an animated scene (frame: {"frame", "fps", "time"};
    its figures are named NAME_fF)."""
    description = SCENES.get(name, "")
    if frame is not None:
        name = f"{name}_f{frame['frame']}"
    if args.coverage:
        name = f"{name}_coverage"
        scene = coverage_copy(scene, out)
        print(f"{name}: coverage: every material a flat emitter, no lights", flush=True)
    if args.lambert_dielectrics:
        scene, changed = without_dielectric_specular(scene, out)
        print(f"{name}: specularFactor 0 on {len(changed)} material(s): "
              f"{', '.join(changed) or 'none'}", flush=True)  # fmt: skip
    print(f"{name}: Cycles ({args.renders} x {args.spp} spp + reference "
          f"{args.reference_spp} spp)", flush=True)  # fmt: skip
    cyc = render_cycles(scene, env, name, args, out, frame)
    print(f"{name}: worker ({args.renders} x {args.spp} spp)", flush=True)
    wrk = render_worker(scene, env, name, args.spp, args, out, "equal-spp", frame)
    spp_t = equal_time_spp(args.spp, float(np.mean(cyc["seconds"])), wrk)
    print(f"{name}: worker at equal time ({args.renders} x {spp_t} spp)", flush=True)
    wrk_t = render_worker(scene, env, name, spp_t, args, out, "equal-time", frame)
    figures = {
        "scene": name,
        "file": str(scene),
        "environment": env,
        "description": description,
        "frame": frame,
        "cycles_imported_keys": cyc["keys"],
        "settings": {k: getattr(args, k) for k in ("width", "height", "spp", "reference_spp",
                                                   "renders", "threads", "max_depth", "grid",
                                                   "cycles_microfacet", "cycles_textures",
                                                   "cycles_volume", "cycles_anisotropy",
                                                   "lambert_dielectrics", "coverage",
                                                   "fps", "guiding")},
        **analyse(cyc, wrk, wrk_t, args, rects),
    }  # fmt: skip
    (out / f"{name}.json").write_text(json.dumps(figures, indent=2) + "\n")
    write_png(out / f"{name}.png", np.mean(wrk["images"], axis=0), np.mean(cyc["images"], axis=0))
    return figures


def fmt(x: float | None, spec: str) -> str:
    return "-" if x is None else format(x, spec)


def print_table(all_figures: list[dict]) -> None:
    head = (f"{'scene':18} {'region':7} {'ch':2} {'ratio':>7} {'+-SE':>7} {'MSE worker':>11} "
            f"{'MSE Cycles':>11} {'eff spp':>8} {'eff time':>8}")  # fmt: skip
    print(head)
    print("-" * len(head))
    for figures in all_figures:
        for r in figures["rows"]:
            print(f"{figures['scene']:18} {r['region']:7} {r['channel']:2} "
                  f"{fmt(r['ratio'], '7.4f')} {fmt(r['ratio_se'], '7.4f')} "
                  f"{fmt(r['worker_mse'], '11.4g')} {fmt(r['cycles_mse'], '11.4g')} "
                  f"{fmt(r['efficiency_ratio_equal_spp'], '8.3g')} "
                  f"{fmt(r['efficiency_ratio_equal_time'], '8.3g')}")  # fmt: skip
    for figures in all_figures:
        print(f"{figures['scene']}: Cycles {np.mean(figures['cycles_seconds']):.3f} s/render, "
              f"worker {np.mean(figures['worker_seconds']):.3f} s/render at equal spp, "
              f"{figures['equal_time_worker_spp']} spp at equal time")  # fmt: skip
    for figures in all_figures:
        e = figures["edges"]
        print(f"{figures['scene']}: luminance MSE on the reference's edges ("
              f"{100 * e['edge_fraction']:.1f} % of the pixels) worker / Cycles "
              f"{e['worker']['mse_edges']:.3g} / {e['cycles']['mse_edges']:.3g}, elsewhere "
              f"{e['worker']['mse_elsewhere']:.3g} / {e['cycles']['mse_elsewhere']:.3g}; "
              f"share on the edges {e['worker']['edge_share']:.2f} / "
              f"{e['cycles']['edge_share']:.2f}")  # fmt: skip


def furthest_block(figures: dict, tolerance: float = 0.005) -> dict | None:
    """The block and channel whose ratio is furthest from 1 in standard errors, among those
    more than tolerance away from 1 (None if none is)."""
    blocks = [r for r in figures["rows"] if r["region"] != "image" and r["ratio"] is not None
              and r["ratio_se"] and abs(r["ratio"] - 1) > tolerance]  # fmt: skip
    return max(blocks, key=lambda r: abs(r["ratio"] - 1) / r["ratio_se"], default=None)


def print_summary(all_figures: list[dict]) -> None:
    """One Markdown row per scene, as docs/parity.md's results table has them."""
    print("| scene | ratio R / G / B (± SE), whole image | furthest block from 1 "
          "| MSE worker / Cycles (G) | efficiency, equal spp / equal time (G) "
          "| by variance, equal spp / equal time (G) |")  # fmt: skip
    print("|---|---|---|---|---|---|")
    for figures in all_figures:
        image = {r["channel"]: r for r in figures["rows"] if r["region"] == "image"}
        se = max(image[c]["ratio_se"] or 0.0 for c in CHANNELS)
        ratios = " / ".join(fmt(image[c]["ratio"], ".3f") for c in CHANNELS)
        block = furthest_block(figures)
        far = ("none more than 0.5 % off" if block is None else
               f"{block['region']} {block['channel']} {block['ratio']:.3f} ± "
               f"{block['ratio_se']:.4f}")  # fmt: skip
        g = image["G"]
        print(f"| `{figures['scene']}` | {ratios} (± {se:.4f}) | {far} "
              f"| {fmt(g['worker_mse'], '.3g')} / {fmt(g['cycles_mse'], '.3g')} "
              f"| {fmt(g['efficiency_ratio_equal_spp'], '.2f')} / "
              f"{fmt(g['efficiency_ratio_equal_time'], '.2f')} "
              f"| {fmt(g.get('variance_efficiency_ratio_equal_spp'), '.2f')} / "
              f"{fmt(g.get('variance_efficiency_ratio_equal_time'), '.2f')} |")  # fmt: skip


def rectangle(text: str) -> tuple[int, int, int, int]:
    try:
        x0, y0, x1, y1 = (int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--region {text!r}: expected X0,Y0,X1,Y1") from None
    if not (0 <= x0 < x1 and 0 <= y0 < y1):
        raise argparse.ArgumentTypeError(f"--region {text!r}: need 0 <= X0 < X1, 0 <= Y0 < Y1")
    return x0, y0, x1, y1


def frame_list(text: str) -> list[int]:
    try:
        frames = [int(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"--frame {text!r}: expected F or F,G,...") from None
    return frames


def frames_of(name: str, args, parity: bool) -> list[dict | None]:
    """The frames to compare of scene name: [None] for a still, else one {"frame", "fps",
    "time"} per frame (--frame, or an animated parity scene's own frames)."""
    animated = ANIMATED.get(name) if parity else None
    frames = [f for group in args.frame for f in group]
    if not frames and animated is None:
        return [None]
    if parity and animated is None:
        return [None]  # a still parity scene (in the suite): --frame is for the animated ones
    fps = args.fps or (animated["fps"] if animated else 24.0)
    frames = frames or list(animated["compare"])
    return [{"frame": f, "fps": fps, "time": f / fps} for f in frames]


def main() -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "scene", nargs="?", help=f"a .gltf/.glb file or a parity scene: {', '.join(SCENES)}"
    )
    parser.add_argument(
        "--suite", action="store_true", help="every parity scene (the default without a scene)"
    )
    parser.add_argument(
        "--realistic",
        action="store_true",
        help=f"the realistic suite ({', '.join(REALISTIC)}; not in --suite) at the settings "
        "of #38's measurement unless given: 320x240, max_depth 13 (12 bounces), 256 spp "
        "against a 4096-spp reference",
    )
    parser.add_argument("--out", type=Path, default=ROOT / "out" / "parity")
    parser.add_argument(
        "--guiding",
        action="store_true",
        help="the worker renders with path guiding (`render --guiding on`; #38); its training "
        "is part of each render's seconds",
    )
    parser.add_argument("--width", type=int, help="default 128 (--realistic: 320)")
    parser.add_argument("--height", type=int, help="default 128 (--realistic: 240)")
    parser.add_argument(
        "--spp", type=int, help="spp of the compared renders (default 64, --realistic: 256)"
    )
    parser.add_argument(
        "--reference-spp",
        type=int,
        default=4096,
        help="spp of the Cycles reference the MSEs are measured against",
    )
    parser.add_argument(
        "--renders",
        type=int,
        default=4,
        help="independent renders per side (seeds 1..K): the noise estimate",
    )
    parser.add_argument("--threads", type=int, default=os.cpu_count() or 1)
    parser.add_argument(
        "--max-depth",
        type=int,
        help="the farm's max_depth; Cycles gets max_depth - 1 bounces (default 8, --realistic: 13)",
    )
    parser.add_argument("--grid", type=int, default=4, help="regions: a grid of N x N blocks")
    parser.add_argument(
        "--region",
        type=rectangle,
        action="append",
        default=[],
        help="a further region X0,Y0,X1,Y1 (pixels, rows from the top)",
    )
    parser.add_argument(
        "--environment",
        type=Path,
        help="an equirectangular .hdr/.exr lighting both renders (as the farm's "
        "environment setting); a parity scene may bring its own",
    )
    parser.add_argument("--environment-intensity", type=float, default=1.0)
    parser.add_argument("--environment-rotation-deg", type=float, default=0.0)
    parser.add_argument(
        "--cycles-microfacet",
        choices=("multi_ggx", "ggx"),
        default="multi_ggx",
        help="Cycles' Principled BSDF distribution: multi_ggx as Blender's importer makes it, "
        "or ggx, the single-scattering GGX of the glTF spec (docs/parity.md)",
    )
    parser.add_argument(
        "--cycles-textures",
        choices=("as_imported", "linear"),
        default="as_imported",
        help="Cycles' 8-bit sRGB textures as imported (filtered, then decoded), or replaced "
        "by linear float copies (decoded, then filtered, as glTF and the farm do; "
        "docs/parity.md)",
    )
    parser.add_argument(
        "--cycles-volume",
        choices=("as_imported", "gltf"),
        default="as_imported",
        help="Cycles' Volume Absorption as Blender's importer maps KHR_materials_volume, or "
        "set to absorb as the extension defines (Beer-Lambert with attenuationColor ^ "
        "(length / attenuationDistance); docs/parity.md)",
    )
    parser.add_argument(
        "--cycles-anisotropy",
        choices=("as_imported", "gltf"),
        default="as_imported",
        help="Cycles' anisotropic Principled BSDFs as Blender's importer maps "
        "KHR_materials_anisotropy (anisotropyStrength as Anisotropic), or set so that "
        "Cycles' two GGX alphas are the extension's (mix(r^2, 1, strength^2) along, r^2 "
        "across; docs/parity.md)",
    )
    parser.add_argument(
        "--frame",
        type=frame_list,
        action="append",
        default=[],
        help="(animated scenes) compare frame F: the worker at --time F / fps, Cycles at "
        "frame F of the imported animation; repeatable, or F,G,... (an animated parity scene "
        "without it: its own frames)",
    )
    parser.add_argument(
        "--fps",
        type=float,
        help="the frame rate of --frame (default: the parity scene's, else 24)",
    )
    parser.add_argument(
        "--coverage",
        action="store_true",
        help="render a copy of each scene in which every material only emits a flat colour "
        "of its own and no light is left: the images are what the camera sees where, so a "
        "difference is geometry (a pose, the camera), not shading (docs/parity.md)",
    )
    parser.add_argument(
        "--lambert-dielectrics",
        action="store_true",
        help="render a copy of each scene in which every opaque dielectric has "
        "KHR_materials_specular specularFactor 0 (the spec's Lambert lobe alone): what it "
        "leaves of a difference is not the diffuse/specular coupling (docs/parity.md)",
    )
    args = parser.parse_args()
    defaults = {"width": 128, "height": 128, "spp": 64, "max_depth": 8}
    if args.realistic:
        defaults = {"width": 320, "height": 240, "spp": 256, "max_depth": 13}
    for key, value in defaults.items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    for key in ("width", "height", "spp", "reference_spp", "threads", "max_depth", "grid"):
        if getattr(args, key) < 1:
            parser.error(f"--{key.replace('_', '-')} must be >= 1")
    if not args.environment_intensity > 0:
        parser.error("--environment-intensity must be > 0")
    if args.renders < 2:
        parser.error("--renders must be >= 2 (the noise is estimated across renders)")
    for x0, y0, x1, y1 in args.region:
        if x1 > args.width or y1 > args.height:
            parser.error(f"--region {x0},{y0},{x1},{y1} is outside the "
                         f"{args.width}x{args.height} image")  # fmt: skip
    if sum([args.suite, args.realistic, bool(args.scene)]) > 1:
        parser.error("give a scene, --suite or --realistic, not two of them")
    if args.scene in SCENES and args.scene not in ANIMATED and args.frame:
        parser.error(f"--frame: {args.scene} is a still scene (animated: {', '.join(ANIMATED)})")
    if args.fps is not None and not args.fps > 0:
        parser.error("--fps must be > 0")
    # Without a scene (as `make bench` runs it): the suite.
    args.suite = args.suite or not (args.scene or args.realistic)
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    if args.environment is not None and not args.environment.is_file():
        parser.error(f"--environment {args.environment}: no such file")
    parity = args.suite or args.realistic or args.scene in SCENES
    if parity:
        if args.suite:
            names = [n for n in SCENES if n not in REALISTIC]
        else:
            names = list(REALISTIC) if args.realistic else [args.scene]
        scenes = generate_scenes(names, out)
    else:
        path = Path(args.scene)
        if not path.is_file():
            parser.error(f"scene {args.scene!r}: neither a file nor a parity scene "
                         f"({', '.join(SCENES)})")  # fmt: skip
        scenes = {path.stem: {"scene": str(path.resolve()), "environment": None}}
        rewrites = args.lambert_dielectrics or args.coverage
        if rewrites and path.read_bytes()[:4] != b"glTF":
            parser.error(f"--lambert-dielectrics, --coverage: {args.scene} is not a GLB; they "
                         "rewrite a self-contained .glb (export the scene as one)")  # fmt: skip
    all_figures = []
    for name, files in scenes.items():
        # A parity scene's own map, else --environment; either with --environment-intensity
        # and --environment-rotation-deg.
        env_map = files["environment"] or (args.environment and str(args.environment.resolve()))
        env = None
        if env_map:
            env = {"path": env_map, "intensity": args.environment_intensity,
                   "rotation_deg": args.environment_rotation_deg}  # fmt: skip
        for frame in frames_of(name, args, parity):
            all_figures.append(
                run_scene(name, Path(files["scene"]), env, args, args.region, out, frame)
            )
    print_table(all_figures)
    print()
    print_summary(all_figures)
    if len(all_figures) > 1:
        (out / "parity.json").write_text(json.dumps(all_figures, indent=2) + "\n")
    if args.suite or args.realistic:
        name = "cycles_parity_lambert" if args.lambert_dielectrics else "cycles_parity"
        name = "cycles_realistic" if args.realistic else name
        name = name + "_coverage" if args.coverage else name
        write_results(name, {f["scene"]: f for f in all_figures})
    print(f"wrote {out}")
    return all_figures


if __name__ == "__main__":
    main()
