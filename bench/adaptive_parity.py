"""Per-pixel adaptive sampling against Cycles' own adaptive sampling, on the realistic suite
(#38): the floor of rough tiles with glass and metal spheres, the interior lit through a window,
the product shot under an HDR environment (bench/support/parity_scenes.py, exported with
Blender's exporter as bench/cycles_parity.py --realistic does), 320x240, 13 bounces.

Per scene:
1. Cycles (bpy, matched settings as cycles_parity.py sets them) with its adaptive sampling at
   Blender's defaults: threshold 0.01, automatic minimum samples, at most 4096 samples; and two
   uniform references at --reference-spp (seeds 1000 and 1001). Its mean spp is read from
   the adaptive render's Debug Sample Count pass.
2. The farm (embedded PostgreSQL, 2 workers of 1 thread: Cycles gets 2 threads): two uniform
   references at --reference-spp, then the same scene with adaptive pixel (--threshold and
   --metric: noise_metric display by default, what this benchmark scores), with adaptive
   pixel_mse and adaptive tile at the same threshold, and uniform at the pixel job's mean spp.
   Render time is the server's elapsed_s (first lease to last merge; the workers keep the
   scene loaded between jobs, so only the first job, a reference, pays its load).
3. Each image is scored on display-referred MSE (the sRGB-encoded image clipped to [0, 1], as a
   PNG or a viewer shows it, in 8-bit levels squared) against its own renderer's reference,
   less the reference's own noise (half the mean squared difference of the two references), so
   the figure is the noise of the estimate rather than the two renderers' model differences
   (docs/parity.md); and, for the record, against Cycles' reference. Efficiency is
   1 / (MSE x seconds); the table gives each run's efficiency over Cycles adaptive's.

Writes bench/results/adaptive_parity.json and out/adaptive_parity/<scene>.json.

    .venv/bin/python bench/adaptive_parity.py [--scene NAME ...] [--threshold 0.04]
        [--metric display|relative] [--reference-spp 1024] [--guiding] [--reuse]
        [--run pixel|pixel_mse|tile|uniform ...] [--setting KEY=VALUE ...]
        [--out out/adaptive_parity]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
from cycles_parity import SUPPORT, generate_scenes, rgb, run_blender
from passes_parity import read_parts
from support.parity_scenes import REALISTIC
from support.results import write_results
from variance_paths import setting

from renderfarm.cli.localfarm import LocalFarm
from renderfarm.client import Client
from renderfarm.infra.images import read_exr, srgb_encode

ROOT = Path(__file__).resolve().parents[1]
WIDTH, HEIGHT, MAX_DEPTH = 320, 240, 13
# Blender's defaults for Cycles' adaptive sampling (bpy 5.0.1: samples 4096, threshold 0.01,
# minimum samples 0, which Cycles takes as automatic).
CYCLES_ADAPTIVE = {"threshold": 0.01, "min_samples": 0}
CYCLES_MAX_SAMPLES = 4096
# The farm's runs: its adaptive modes, and uniform sampling at the pixel job's mean spp.
RUNS = ("pixel", "pixel_mse", "tile", "uniform")


def display(image: np.ndarray) -> np.ndarray:
    """The image as a viewer shows it: sRGB-encoded, clipped, in 8-bit levels."""
    return srgb_encode(image) * 255.0


def display_mse(image: np.ndarray, refs: tuple[np.ndarray, np.ndarray]) -> float:
    """Display MSE against the first reference, less that reference's own noise (estimated as
    half the mean squared difference of the two independent references)."""
    a, b = display(refs[0]), display(refs[1])
    noise = float(np.mean((a - b) ** 2)) / 2.0
    return float(np.mean((display(image) - a) ** 2)) - noise


def render_cycles(scene: Path, env: dict | None, name: str, args, out: Path) -> dict:
    """Cycles adaptive, then the two references; their images and seconds (--reuse: those of
    an earlier run into the same --out, when there are)."""
    scratch = out / "renders" / name
    scratch.mkdir(parents=True, exist_ok=True)
    kept = scratch / "cycles-result.json"
    renders = [
        {"spp": CYCLES_MAX_SAMPLES, "seed": 1, "path": str(scratch / "cycles-adaptive.exr"),
         "adaptive": CYCLES_ADAPTIVE,
         "sample_count_path": str(scratch / "cycles-adaptive-passes.exr")},
        *({"spp": args.reference_spp, "seed": 1000 + k,
           "path": str(scratch / f"cycles-reference-{k}.exr")} for k in range(2)),
    ]  # fmt: skip
    config = {"scene": str(scene), "width": WIDTH, "height": HEIGHT, "max_depth": MAX_DEPTH,
              "threads": 2, "renders": renders, "environment": env, "microfacet": "multi_ggx",
              "textures": "as_imported", "volume": "gltf", "anisotropy": "gltf"}  # fmt: skip
    path = scratch / "cycles.json"
    if args.reuse and kept.is_file() and json.loads(kept.read_text())["config"] == config:
        result = json.loads(kept.read_text())["result"]
        print(f"{name}: Cycles' renders of an earlier run reused", flush=True)
    else:
        path.write_text(json.dumps(config))
        result = run_blender(SUPPORT / "cycles_render.py", [str(path)], out,
                             f"Cycles rendering {scene}")  # fmt: skip
        kept.write_text(json.dumps({"config": config, "result": result}))
    images = [rgb(Path(r["path"])) for r in renders]
    counts = cycles_spp(Path(renders[0]["sample_count_path"]))
    return {"adaptive": images[0], "seconds": result["seconds"][0], "refs": tuple(images[1:]),
            "spp": float(np.mean(counts)), "spp_map": counts}  # fmt: skip


def cycles_spp(path: Path) -> np.ndarray:
    """Cycles' samples per pixel: its Debug Sample Count pass holds each pixel's count over the
    render's sample count."""
    (count,) = [v for k, v in read_parts(path).items() if ".Debug Sample Count." in k]
    return np.asarray(count, dtype=np.float64) * CYCLES_MAX_SAMPLES


def pixel_display_mse(image: np.ndarray, refs: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Each pixel's display MSE (8-bit levels squared, averaged over RGB), estimated without
    bias from two independent references a and b as (x - a)(x - b): its expectation is the
    image's squared error, the references' own noise cancelling pixel by pixel (a single
    pixel's estimate may be negative; means over regions are what it is for)."""
    x, a, b = display(image), display(refs[0]), display(refs[1])
    return np.mean((x - a) * (x - b), axis=-1)


# The regions of allocation(): log2(Cycles' samples / the farm's) of a pixel in each.
ALLOCATION_REGIONS = (("farm >= 4x Cycles' samples", -np.inf, -2.0),
                      ("farm 2-4x", -2.0, -1.0), ("within 2x", -1.0, 1.0),
                      ("Cycles 2-4x", 1.0, 2.0), ("Cycles >= 4x", 2.0, np.inf))  # fmt: skip


def allocation(farm: dict, cycles: dict) -> list[dict]:
    """Where a farm adaptive job and Cycles' adaptive render spend their samples and where
    their errors are, by region of the ratio of their per-pixel sample counts: per region its
    share of the pixels, and per side the mean spp, the mean display MSE per pixel
    (pixel_display_mse(), each side against its own references) and its shares of the side's samples
    and of its MSE. Says whether a gap is the allocation (one side's samples where the other
    spends few) or the noise per sample (equal samples, unequal MSE)."""
    ratio = np.log2(np.maximum(cycles["spp_map"], 1.0) / np.maximum(farm["spp_map"], 1.0))
    sides = {}
    for side, run in (("farm", farm), ("cycles", cycles)):
        mse = pixel_display_mse(run["image"], run["own"])
        sides[side] = (run["spp_map"], np.sum(run["spp_map"]), mse, float(np.sum(mse)))
    rows = []
    for label, lo, hi in ALLOCATION_REGIONS:
        inside = (ratio >= lo) & (ratio < hi)  # the ratio is finite: counts are at least 1
        row = {"region": label, "pixels": float(np.mean(inside))}
        for side, (spp, spp_total, mse, mse_total) in sides.items():
            row[side] = {
                "mean_spp": float(np.mean(spp[inside])) if inside.any() else None,
                "mse_per_pixel": float(np.mean(mse[inside])) if inside.any() else None,
                "samples_share": float(np.sum(spp[inside]) / spp_total),
                "mse_share": float(np.sum(mse[inside]) / mse_total) if mse_total else None,
            }
        rows.append(row)
    return rows


def render_farm(client: Client, scene: Path, env: dict | None, name: str, scratch: Path,
                reuse: bool = False, **settings) -> tuple[dict, np.ndarray]:  # fmt: skip
    """A farm job; its record and image (reuse: an earlier run's, from the same settings). The
    record's "spp_map" is the image's per-pixel samples (its EXR's spp channel)."""
    path = scratch / f"{name}.exr"
    record = scratch / f"{name}.json"
    if reuse and path.is_file() and record.is_file():
        job = json.loads(record.read_text())
        if job["settings_asked"] == settings:
            print(f"{name}: an earlier run's image reused", flush=True)
            return read_farm_image(path, job)
    base = {"width": WIDTH, "height": HEIGHT, "max_depth": MAX_DEPTH, "tile_size": 32,
            "seed": 1}  # fmt: skip
    if env:
        base |= {"environment": env["path"], "environment_intensity": env["intensity"],
                 "environment_rotation_deg": env["rotation_deg"]}  # fmt: skip
    job = client.submit(scene, settings={**base, **settings}, name=name)
    job = client.wait(job["id"], poll_s=0.2, timeout_s=7200)
    if job["state"] != "completed":
        raise SystemExit(f"{name}: the job ended {job['state']}: {job.get('error')}")
    path.write_bytes(client.image(job["id"], "exr"))
    record.write_text(json.dumps({**job, "settings_asked": settings}))
    return read_farm_image(path, job)


def read_farm_image(path: Path, job: dict) -> tuple[dict, np.ndarray]:
    ch = read_exr(str(path))
    job["spp_map"] = np.asarray(ch["spp"], dtype=np.float64)
    return job, np.stack([ch[c] for c in "RGB"], axis=-1).astype(np.float64)


def run_scene(client: Client, name: str, files: dict, args, out: Path) -> dict:
    scene = Path(files["scene"])
    env = None
    if files["environment"]:
        env = {"path": files["environment"], "intensity": 1.0, "rotation_deg": 0.0}
    print(
        f"{name}: Cycles adaptive (threshold {CYCLES_ADAPTIVE['threshold']}, at most "
        f"{CYCLES_MAX_SAMPLES} spp) and 2 references at {args.reference_spp} spp",
        flush=True,
    )
    cyc = render_cycles(scene, env, name, args, out)
    scratch = out / "renders" / name
    extra = {"guiding": True} if args.guiding else {}
    print(f"{name}: the farm's references ({args.reference_spp} spp)", flush=True)
    refs = tuple(
        render_farm(client, scene, env, f"{name}-reference-{k}", scratch, args.reuse,
                    noise_threshold=0, max_spp=args.reference_spp, seed=1000 + k, **extra)[1]
        for k in range(2)
    )  # fmt: skip
    runs = {"cycles adaptive": {"image": cyc["adaptive"], "seconds": cyc["seconds"],
                                "spp": cyc["spp"], "own": cyc["refs"],
                                "spp_map": cyc["spp_map"]}}  # fmt: skip
    adaptive = {"noise_threshold": args.threshold, "noise_metric": args.metric,
                "max_spp": CYCLES_MAX_SAMPLES, **dict(args.setting)}  # fmt: skip
    for label, mode in (("farm pixel", "pixel"), ("farm pixel_mse", "pixel_mse"),
                        ("farm tile", "tile")):  # fmt: skip
        if mode not in args.run:
            continue
        print(f"{name}: {label} ({args.metric} error, threshold {args.threshold})", flush=True)
        job, image = render_farm(client, scene, env, f"{name}-{mode}-{args.metric}", scratch,
                                 adaptive=mode, **adaptive, **extra)  # fmt: skip
        runs[label] = {"image": image, "seconds": job["progress"]["elapsed_s"],
                       "spp": job["progress"]["mean_spp"], "own": refs,
                       "spp_map": job["spp_map"]}  # fmt: skip
    if "uniform" in args.run:
        # At the mean spp of the pixel job, or of the first adaptive job run.
        first = next(label for label in runs if label.startswith("farm "))
        spp = max(1, round(runs[first]["spp"]))
        print(f"{name}: farm uniform ({spp} spp, the {first} job's mean)", flush=True)
        job, image = render_farm(client, scene, env, f"{name}-uniform-{spp}", scratch,
                                 noise_threshold=0, max_spp=spp, **extra)  # fmt: skip
        runs["farm uniform"] = {"image": image, "seconds": job["progress"]["elapsed_s"],
                                "spp": job["progress"]["mean_spp"], "own": refs}  # fmt: skip
    figures = {}
    for label, run in runs.items():
        own = display_mse(run["image"], run["own"])
        vs_cycles = display_mse(run["image"], cyc["refs"])
        figures[label] = {
            "seconds": run["seconds"],
            "mean_spp": run["spp"],
            "display_mse": own,
            "display_mse_vs_cycles_reference": vs_cycles,
            "efficiency": 1.0 / (own * run["seconds"]) if own > 0 else None,
        }
    base = figures["cycles adaptive"]["efficiency"]
    for f in figures.values():
        f["efficiency_vs_cycles_adaptive"] = f["efficiency"] / base if base else None
    result = {"scene": name, "threshold": args.threshold, "noise_metric": args.metric,
              "reference_spp": args.reference_spp, "guiding": args.guiding,
              "settings": dict(args.setting), "runs": figures,
              "allocation": {label: allocation(run, runs["cycles adaptive"])
                             for label, run in runs.items()
                             if label in ("farm pixel", "farm pixel_mse")}}  # fmt: skip
    (out / f"{name}.json").write_text(json.dumps(result, indent=2) + "\n")
    return result


def print_table(results: list[dict]) -> None:
    print(f"{'scene':18} {'run':16} {'seconds':>8} {'mean spp':>9} {'display MSE':>12} "
          f"{'vs Cycles ref':>13} {'efficiency / Cycles adaptive':>29}")  # fmt: skip
    for r in results:
        for label, f in r["runs"].items():
            spp = f"{f['mean_spp']:.0f}" if f["mean_spp"] is not None else "-"
            ratio = f["efficiency_vs_cycles_adaptive"]
            print(f"{r['scene']:18} {label:16} {f['seconds']:8.1f} {spp:>9} "
                  f"{f['display_mse']:12.3f} {f['display_mse_vs_cycles_reference']:13.3f} "
                  f"{'-' if ratio is None else f'{ratio:.2f}':>29}")  # fmt: skip


def print_allocation(results: list[dict]) -> None:
    for r in results:
        for label, rows in r["allocation"].items():
            print(
                f"\n{r['scene']}: {label} against Cycles adaptive, by region of the ratio of "
                "their samples per pixel (display MSE per pixel, 8-bit levels squared)"
            )
            print(f"{'region':28} {'pixels':>7} {'farm spp':>9} {'MSE/px':>7} {'MSE %':>6} "
                  f"{'Cycles spp':>10} {'MSE/px':>7} {'MSE %':>6}")  # fmt: skip
            for row in rows:
                if not row["pixels"]:
                    continue
                f, c = row["farm"], row["cycles"]
                print(f"{row['region']:28} {row['pixels']:7.1%} {f['mean_spp']:9.0f} "
                      f"{f['mse_per_pixel']:7.2f} {f['mse_share'] or 0:6.1%} "
                      f"{c['mean_spp']:10.0f} {c['mse_per_pixel']:7.2f} "
                      f"{c['mse_share'] or 0:6.1%}")  # fmt: skip


def main() -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", action="append", choices=list(REALISTIC),
                        help="a scene of the realistic suite (default: all three)")  # fmt: skip
    parser.add_argument("--threshold", type=float, default=0.004,
                        help="the farm jobs' noise_threshold (default 0.004)")  # fmt: skip
    parser.add_argument("--metric", choices=("display", "relative"), default="display",
                        help="the farm jobs' noise_metric (default display)")  # fmt: skip
    parser.add_argument("--reuse", action="store_true",
                        help="reuse Cycles' renders and the farm's references of an earlier "
                        "run into the same --out (made with the same settings)")  # fmt: skip
    parser.add_argument("--reference-spp", type=int, default=1024)
    parser.add_argument("--guiding", action="store_true", help="path guiding on the farm's jobs")
    parser.add_argument("--setting", action="append", type=setting, default=[],
                        metavar="KEY=VALUE",
                        help="a job setting of the farm's adaptive runs (repeatable; the value "
                        "JSON when it parses), to measure a change before and after")  # fmt: skip
    parser.add_argument("--run", action="append", choices=RUNS,
                        help="a farm run to make (repeatable; default: all four; uniform "
                        "needs an adaptive run for its spp)")  # fmt: skip
    parser.add_argument("--out", type=Path, default=ROOT / "out" / "adaptive_parity")
    args = parser.parse_args()
    if not 0 < args.threshold <= 1:
        parser.error("--threshold must be in (0, 1]")
    args.run = args.run or list(RUNS)
    if set(args.run) == {"uniform"}:
        parser.error("--run uniform takes its spp from an adaptive run: name one too")
    if args.reference_spp < 16:
        parser.error("--reference-spp must be >= 16")
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    names = args.scene or list(REALISTIC)
    scenes = generate_scenes(names, out)
    results = []
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        with LocalFarm(workers=2, data_dir=Path(tmp) / "farm", threads=1) as farm:
            with Client(farm.url, timeout=120) as client:
                for name in names:
                    results.append(run_scene(client, name, scenes[name], args, out))
    print()
    print_table(results)
    print_allocation(results)
    print(f"({time.perf_counter() - start:.0f} s)")
    write_results("adaptive_parity", {r["scene"]: r for r in results})
    return results


if __name__ == "__main__":
    main()
