"""USD parity (#41): each stage of a USD corpus rendered by the farm and by Cycles through
Blender's own USD importer, at matched settings, with the Cycles parity harness's statistics.

    .venv/bin/python bench/usd_parity.py DIR [--out out/usd-parity] [--only NAME]
        [--height 96] [--spp 32] [--reference-spp 1024] [--renders 2] [--threads 2]
        [--worker PATH] [--cycles-lights as_imported|usd] [--cycles-microfacet ...]

DIR holds the stages (none are in the repository): a USD file (.usd, .usda, .usdc, .usdz) is a
stage; so is a folder, whose root layer is the layer named after the folder nearest its top,
else the one layer nearest its top (the farm's bundle rule). Per stage:

1. A bundle is laid out as a user would upload it: a top layer `parity.usda` that sublayers the
   stage (copied under `stage/`, a .usdz unpacked) and repeats its root layer's metadata
   (upAxis, metersPerUnit, time codes, render settings); where the stage has no camera, the top
   layer adds one framing the stage's bounds, and where it has no light, a white dome (radiance
   1) and a rect light. Both renderers read this same layer.
2. The farm: the server's converter (infra/usd_import.py UsdImporter, the child process under
   the server's limits) turns the bundle into a GLB, or refuses it; `renderfarm-worker inspect`
   accepts or refuses the GLB as the server does; then `renderfarm-worker render` (the job
   settings the server derives: the dome as the environment map with its intensity and turn,
   the camera's depth of field).
3. Cycles: bpy.ops.wm.usd_import (bench/support/cycles_render.py, "importer": "usd": Blender's
   defaults, subdivision not applied, a dome light as the world) through the camera the
   converter chose, rendered with the settings bench/cycles_parity.py matches to the farm's path
   tracer (box filter, max_depth - 1 bounces, no clamping, no denoising, Standard view, ...).
   The image's aspect is the camera's apertures'. An animated stage is compared at its start
   time code (the worker at --time start / timeCodesPerSecond, Cycles at that frame).
4. The statistics of bench/cycles_parity.py (analyse: per region and channel the mean ratio
   worker / Cycles with its standard error, the MSE of one render against a Cycles reference at
   --reference-spp, the error at the reference's edges apart), and what Blender's importer made
   of each light (type, power, size), which names a difference in light.

Writes OUT/NAME.json, OUT/NAME.png (worker | Cycles | ratio heat map) and OUT/usd_parity.json
(also bench/results/usd_parity.json, the whole corpus without --only); prints the table of
docs/parity.md ("USD stages").
"""

from __future__ import annotations

import argparse
import asyncio
import copy
import datetime
import io
import json
import math
import os
import shutil
import subprocess
import sys
import zipfile
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cycles_parity import (  # noqa: E402
    analyse,
    equal_time_spp,
    fmt,
    furthest_block,
    render_cycles,
    render_worker,
    write_png,
)
from support.results import write_results  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
LAYER_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")
# The added camera: a 35 mm lens on a 36 x 24 mm back (in tenths of a scene unit), looking at
# the bounds' centre from this direction (Y up; turned for a Z-up stage).
CAMERA_DIRECTION = (0.55, 0.45, 1.0)
FOCAL, H_APERTURE, V_APERTURE = 35.0, 36.0, 24.0


# ------------------------------------------------------------------ the stages


def find_stages(root: Path) -> list[tuple[str, Path, Path]]:
    """(name, folder or file, root layer) of each stage under root."""
    stages = []
    for entry in sorted(root.iterdir()):
        if entry.is_file() and entry.suffix.lower() in LAYER_SUFFIXES:
            stages.append((entry.stem, entry, entry))
        elif entry.is_dir():
            layers = [p for p in entry.rglob("*") if p.suffix.lower() in LAYER_SUFFIXES]
            if not layers:
                continue

            def depth(p: Path, entry: Path = entry) -> int:
                return len(p.relative_to(entry).parts)

            named = sorted((p for p in layers if p.stem == entry.name), key=depth)
            top = min(depth(p) for p in layers)
            nearest = [p for p in layers if depth(p) == top]
            if named:
                stages.append((entry.name, entry, named[0]))
            elif len(nearest) == 1:
                stages.append((entry.name, entry, nearest[0]))
            else:
                print(f"{entry.name}: skipped, several layers nearest its top "
                      f"({', '.join(p.name for p in nearest)})", file=sys.stderr)  # fmt: skip
    return stages


def lay_out(name: str, source: Path, root_layer: Path, out: Path) -> tuple[Path, list[str]]:
    """The bundle's folder: the stage under stage/ (a .usdz unpacked), and parity.usda on top.
    Returns the top layer's path and what it adds ("camera", "lights")."""
    from pxr import Sdf, Usd, UsdGeom

    bundle = out / "stages" / name
    shutil.rmtree(bundle, ignore_errors=True)
    (bundle / "stage").mkdir(parents=True)
    if source.is_dir():
        shutil.copytree(source, bundle / "stage", dirs_exist_ok=True)
        rel = root_layer.relative_to(source)
    else:
        shutil.copy2(source, bundle / "stage" / source.name)
        rel = Path(source.name)
    if rel.suffix.lower() == ".usdz":
        # A package's first entry is its root layer; its files are named relative to it.
        unpacked = bundle / "stage" / rel.with_suffix("")
        with zipfile.ZipFile(bundle / "stage" / rel) as package:
            first = package.namelist()[0]
            package.extractall(unpacked)
        (bundle / "stage" / rel).unlink()
        rel = unpacked.relative_to(bundle / "stage") / first
    stage_layer = Sdf.Layer.FindOrOpen(str(bundle / "stage" / rel))
    top = Sdf.Layer.CreateNew(str(bundle / "parity.usda"))
    top.subLayerPaths.append(f"./stage/{rel.as_posix()}")
    keys = ("upAxis", "metersPerUnit", "timeCodesPerSecond", "framesPerSecond",
            "startTimeCode", "endTimeCode", "renderSettingsPrimPath", "defaultPrim")  # fmt: skip
    for key in keys:
        if stage_layer.pseudoRoot.HasInfo(key):
            top.pseudoRoot.SetInfo(key, stage_layer.pseudoRoot.GetInfo(key))
    top.Save()
    stage = Usd.Stage.Open(top)
    prims = list(stage.Traverse())
    added = []
    if not any(p.IsA(UsdGeom.Camera) for p in prims):
        add_camera(stage)
        added.append("camera")
    if not any(p.HasAPI(_light_api()) for p in prims):
        add_lights(stage)
        added.append("lights")
    stage.GetRootLayer().Save()
    return bundle / "parity.usda", added


def _light_api():
    from pxr import UsdLux

    return UsdLux.LightAPI


def _bounds(stage):
    from pxr import UsdGeom

    cache = UsdGeom.BBoxCache(stage.GetStartTimeCode(), ["default", "render"])
    box = cache.ComputeWorldBound(stage.GetPseudoRoot()).ComputeAlignedRange()
    lo, hi = np.array(box.GetMin()), np.array(box.GetMax())
    if box.IsEmpty() or not np.isfinite(lo).all() or not np.isfinite(hi).all():
        lo, hi = -np.ones(3), np.ones(3)
    return (lo + hi) / 2, max(float(np.linalg.norm(hi - lo)) / 2, 1e-6)


def _view(stage, distance: float):
    """(eye, centre, up) of a view from CAMERA_DIRECTION at distance from the bounds' centre."""
    from pxr import UsdGeom

    centre, radius = _bounds(stage)
    d = np.array(CAMERA_DIRECTION, dtype=float)
    up = np.array([0.0, 1.0, 0.0])
    if UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z:  # (x, y, z) Y-up is (x, -z, y) Z-up
        d, up = np.array([d[0], -d[2], d[1]]), np.array([0.0, 0.0, 1.0])
    d /= np.linalg.norm(d)
    return centre + d * distance * radius, centre, up, radius


def _look_at(prim, eye, centre, up) -> None:
    from pxr import Gf, UsdGeom

    view = Gf.Matrix4d().SetLookAt(Gf.Vec3d(*eye), Gf.Vec3d(*centre), Gf.Vec3d(*up))
    UsdGeom.Xformable(prim).AddTransformOp().Set(view.GetInverse())


def add_camera(stage) -> None:
    """A camera whose vertical field of view holds the bounds' sphere with a margin."""
    from pxr import Gf, UsdGeom

    half = math.atan(V_APERTURE / (2 * FOCAL))
    eye, centre, up, radius = _view(stage, 1.15 / math.sin(half))
    camera = UsdGeom.Camera.Define(stage, "/ParityCamera")
    camera.CreateFocalLengthAttr(FOCAL)
    camera.CreateHorizontalApertureAttr(H_APERTURE)
    camera.CreateVerticalApertureAttr(V_APERTURE)
    distance = float(np.linalg.norm(eye - centre))
    camera.CreateClippingRangeAttr(Gf.Vec2f(distance * 0.01, distance + 10 * radius))
    _look_at(camera.GetPrim(), eye, centre, up)


def add_lights(stage) -> None:
    """A white dome of radiance 1 and a rect light (unnormalized: radiance = intensity) above
    and beside the camera, giving about 3 of irradiance at the bounds' centre."""
    from pxr import Gf, UsdLux

    dome = UsdLux.DomeLight.Define(stage, "/ParityLights/Dome")
    dome.CreateIntensityAttr(1.0)
    dome.CreateColorAttr(Gf.Vec3f(1.0, 1.0, 1.0))
    eye, centre, up, radius = _view(stage, 4.0)
    eye = eye + up * 3.0 * radius  # above the camera's view: shadows fall down and back
    rect = UsdLux.RectLight.Define(stage, "/ParityLights/Key")
    side = 1.5 * radius
    rect.CreateWidthAttr(side)
    rect.CreateHeightAttr(side)
    distance = float(np.linalg.norm(eye - centre))
    rect.CreateIntensityAttr(3.0 * distance**2 / side**2)
    _look_at(rect.GetPrim(), eye, centre, up)


def bundle_bytes(folder: Path) -> bytes:
    """The folder as a zip upload (parity.usda the one layer at its top)."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
        for path in sorted(folder.rglob("*")):
            if path.is_file():
                archive.write(path, path.relative_to(folder).as_posix())
    return buffer.getvalue()


# ------------------------------------------------------------------ the farm's side


def convert(folder: Path, name: str, scratch: Path):
    """The server's conversion of the bundle (UsdImport) or its refusal (SceneError)."""
    from renderfarm.infra.config import Settings
    from renderfarm.infra.usd_import import UsdImporter

    defaults = Settings.model_fields
    importer = UsdImporter(
        scratch,
        cpu_seconds=defaults["scene_inspect_cpu_s"].default,
        memory_mb=int(defaults["max_scene_memory_mb"].get_default(call_default_factory=True)),
        max_output_bytes=defaults["max_upload_bytes"].default,
    )
    return asyncio.run(importer.convert(bundle_bytes(folder), f"{name}.zip"))


def inspect(worker: str, glb: Path) -> dict:
    """`renderfarm-worker inspect --json`: the farm's acceptance of the GLB."""
    proc = subprocess.run([worker, "inspect", str(glb), "--json"], capture_output=True, text=True)
    try:
        return json.loads(proc.stdout.strip().splitlines()[-1])
    except (ValueError, IndexError):
        return {"ok": False, "error": f"inspect exited {proc.returncode}: {proc.stderr[-300:]}"}


def glb_document(glb: bytes) -> dict:
    import struct

    length = struct.unpack_from("<I", glb, 12)[0]
    return json.loads(glb[20 : 20 + length])


def warning_kinds(warnings: list[str]) -> list[str]:
    """Each distinct conversion warning's text without its prim path, with its count."""
    counts = Counter(w.split(": ", 1)[-1] for w in warnings)
    return [f"{text} (x{n})" if n > 1 else text for text, n in counts.items()]


# ------------------------------------------------------------------ one stage


def run_stage(name: str, source: Path, root_layer: Path, args, out: Path) -> dict:
    figures: dict = {"stage": name, "source": str(source), "root_layer": str(root_layer)}
    top, figures["added"] = lay_out(name, source, root_layer, out)
    from renderfarm.errors import SceneError

    scratch = out / "scratch"
    try:
        usd = convert(top.parent, name, scratch)
    except SceneError as e:
        figures.update(accepted=False, error=f"conversion: {e.message}", warnings=[])
        print(f"{name}: REFUSED by the converter: {e.message}", flush=True)
        return figures
    figures["warnings"] = usd.warnings
    glb = out / "stages" / f"{name}.glb"
    glb.write_bytes(usd.glb)
    answer = inspect(args.worker, glb)
    figures["loader_warnings"] = answer.get("warnings", [])
    if not answer.get("ok"):
        figures.update(accepted=False, error=f"inspect: {answer.get('error', '')}")
        print(f"{name}: REFUSED by the loader: {figures['error']}", flush=True)
        return figures
    figures["accepted"] = True
    doc = glb_document(usd.glb)
    camera = (doc.get("cameras") or [{}])[0]
    perspective = camera.get("perspective", {})
    aspect = perspective.get("aspectRatio") or H_APERTURE / V_APERTURE
    sargs = copy.copy(args)
    sargs.height = args.height
    sargs.width = max(8, round(args.height * aspect))
    figures["camera"] = {"prim": camera.get("name"), "yfov": perspective.get("yfov"),
                         "aspect": aspect, "depth_of_field": usd.camera}  # fmt: skip
    env = None
    if usd.environment_data is not None:
        env_path = out / "stages" / f"{name}-environment{Path(usd.environment_filename).suffix}"
        env_path.write_bytes(usd.environment_data)
        env = {"path": str(env_path),
               "intensity": usd.environment["environment_intensity"],
               "rotation_deg": usd.environment["environment_rotation_deg"]}  # fmt: skip
    figures["environment"] = env
    extra_args: tuple[str, ...] = ()
    if usd.camera.get("aperture_radius"):
        extra_args = ("--aperture-radius", repr(usd.camera["aperture_radius"]),
                      "--focus-distance", repr(usd.camera.get("focus_distance", 1.0)))  # fmt: skip
    frame = None
    if doc.get("animations"):
        from pxr import Usd

        stage = Usd.Stage.Open(str(top))
        start, rate = stage.GetStartTimeCode(), stage.GetTimeCodesPerSecond()
        frame = {"frame": int(round(start)), "fps": rate, "time": start / rate}
    figures["frame"] = frame
    cycles_camera = (camera.get("name") or "").rsplit("/", 1)[-1] or None
    extra = {"importer": "usd", "camera": cycles_camera, "world": "as_imported",
             "lights": args.cycles_lights}  # fmt: skip
    print(f"{name}: Cycles ({args.renders} x {args.spp} spp + reference "
          f"{args.reference_spp} spp) at {sargs.width}x{sargs.height}", flush=True)  # fmt: skip
    try:
        cyc = render_cycles(top, None, name, sargs, out, frame, extra)
    except SystemExit as e:  # run_blender's message: the import or render failed
        figures.update(cycles_error=str(e)[-2000:])
        print(f"{name}: Cycles failed: {str(e)[-300:]}", flush=True)
        return figures
    figures["blender_lights"] = cyc["lights"]
    print(f"{name}: worker ({args.renders} x {args.spp} spp)", flush=True)
    wrk = render_worker(glb, env, name, args.spp, sargs, out, "equal-spp", frame, extra_args)
    spp_t = equal_time_spp(args.spp, float(np.mean(cyc["seconds"])), wrk)
    wrk_t = render_worker(glb, env, name, spp_t, sargs, out, "equal-time", frame, extra_args)
    figures["settings"] = {k: getattr(sargs, k) for k in ("width", "height", "spp",
                           "reference_spp", "renders", "threads", "max_depth", "grid",
                           "cycles_microfacet", "cycles_textures", "cycles_lights")}  # fmt: skip
    figures.update(analyse(cyc, wrk, wrk_t, sargs, []))
    write_png(out / f"{name}.png", np.mean(wrk["images"], axis=0), np.mean(cyc["images"], axis=0))
    (out / f"{name}.json").write_text(json.dumps(figures, indent=2) + "\n")
    return figures


# ------------------------------------------------------------------ the table


def row(figures: dict) -> str:
    warnings = "; ".join(warning_kinds(figures.get("warnings", []))) or "-"
    warnings = warnings.replace("|", "\\|")
    added = ", ".join(figures.get("added", [])) or "-"
    if not figures.get("accepted"):
        error = figures["error"][:200].replace("|", "\\|")
        return f"| {figures['stage']} | {added} | **refused**: {error} | - | - | - |"
    if "rows" not in figures:
        return (f"| {figures['stage']} | {added} | {warnings} | Cycles failed: "
                f"{figures.get('cycles_error', '')[-120:]} | - | - |")  # fmt: skip
    image = {r["channel"]: r for r in figures["rows"] if r["region"] == "image"}
    ratios = " / ".join(fmt(image[c]["ratio"], ".3f") for c in "RGB")
    se = max(image[c]["ratio_se"] or 0.0 for c in "RGB")
    block = furthest_block(figures)
    far = "none more than 0.5 % off"
    if block is not None:
        far = (f"{block['region']} {block['channel']} {block['ratio']:.3f} "
               f"± {block['ratio_se']:.3f}")  # fmt: skip
    g = image["G"]
    mse = f"{fmt(g['worker_mse'], '.3g')} / {fmt(g['cycles_mse'], '.3g')}"
    return f"| {figures['stage']} | {added} | {warnings} | {ratios} (± {se:.3f}) | {far} | {mse} |"


def markdown(all_figures: list[dict]) -> str:
    lines = [
        "| stage | added by the bench | conversion warnings | ratio worker / Cycles R / G / B "
        "(± SE), image | furthest block | MSE worker / Cycles (G) |",
        "|---|---|---|---|---|---|",
    ]
    return "\n".join(lines + [row(f) for f in all_figures])


def main() -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dir", type=Path, nargs="?", help="folder of USD stages (files or folders)")
    parser.add_argument(
        "--probes",
        action="store_true",
        help="(instead of DIR) the light probes of bench/support/usd_probes.py: one light "
        "over a Lambertian floor each",
    )
    parser.add_argument("--out", type=Path, default=ROOT / "out" / "usd-parity")
    parser.add_argument("--only", action="append", default=[], help="only this stage (repeatable)")
    parser.add_argument("--height", type=int, default=96, help="image height (width: aspect)")
    parser.add_argument("--spp", type=int, default=32)
    parser.add_argument("--reference-spp", type=int, default=1024)
    parser.add_argument("--renders", type=int, default=2, help="independent renders per side")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--max-depth", type=int, default=8)
    parser.add_argument("--grid", type=int, default=4, help="regions: a grid of N x N blocks")
    parser.add_argument("--worker", default=os.environ.get("RENDERFARM_WORKER_BINARY",
                        str(ROOT / "build/worker/renderfarm-worker")))  # fmt: skip
    parser.add_argument(
        "--cycles-microfacet",
        choices=("multi_ggx", "ggx"),
        default="multi_ggx",
        help="as bench/cycles_parity.py: the importer's multiple-scattering GGX, or GGX",
    )
    parser.add_argument(
        "--cycles-textures",
        choices=("as_imported", "linear"),
        default="as_imported",
        help="as bench/cycles_parity.py: 8-bit sRGB textures as imported, or linear copies",
    )
    parser.add_argument(
        "--cycles-lights",
        choices=("as_imported", "usd"),
        default="as_imported",
        help="Blender's lights as its USD importer makes them, or with its departures from "
        "UsdLux undone (a distant light's strength / 4 and angle / 2, a sphere light's radius "
        "in metres; docs/parity.md)",
    )
    args = parser.parse_args()
    if args.renders < 2:
        parser.error("--renders must be >= 2 (the noise is estimated across renders)")
    if not Path(args.worker).is_file():
        sys.exit(f"{args.worker} not found: build the worker (make worker) or pass --worker")
    # render_worker reads the worker from RENDERFARM_WORKER_BINARY.
    os.environ["RENDERFARM_WORKER_BINARY"] = str(Path(args.worker).resolve())
    args.cycles_volume, args.cycles_anisotropy = "as_imported", "as_imported"
    if (args.dir is None) == (not args.probes):
        parser.error("give DIR or --probes")
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    if args.probes:
        from support.usd_probes import write_probes

        write_probes(out / "probes")
        args.dir = out / "probes"
    stages = [s for s in find_stages(args.dir.resolve()) if not args.only or s[0] in args.only]
    if not stages:
        sys.exit(f"no USD stage under {args.dir}")
    all_figures = []
    for i, (name, source, root_layer) in enumerate(stages, 1):
        print(f"[{i}/{len(stages)}] {name}", flush=True)
        all_figures.append(run_stage(name, source, root_layer, args, out))
    print()
    print(markdown(all_figures))
    summary = {
        "benchmark": "usd_parity",
        "date": datetime.date.today().isoformat(),
        "command": " ".join(["bench/usd_parity.py", *sys.argv[1:]]),
        "stages": all_figures,
    }
    (out / "usd_parity.json").write_text(json.dumps(summary, indent=2) + "\n")
    if not args.only:
        write_results("usd_parity_probes" if args.probes else "usd_parity", summary)
    print(f"wrote {out}")
    return all_figures


if __name__ == "__main__":
    main()
