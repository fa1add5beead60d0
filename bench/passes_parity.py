"""The lobe and light-group outputs (#40) against Cycles' passes on the same glTF scene.

For each scene (a parity scene of bench/support/parity_scenes.py by name; default `combined`,
every material feature under an environment map and two lights):
1. Cycles (bpy in .venv-blender) imports it with Blender's glTF importer at the settings
   bench/cycles_parity.py matches to the farm's path tracer, with its Diffuse, Glossy and
   Transmission Direct/Indirect/Color passes, Emit and Env, and a light group per light and
   emissive object (named as the farm names the glTF node's group) and the world's
   (bench/support/cycles_render.py, CONFIG "passes"), at --reference-spp.
2. A local farm (embedded PostgreSQL, one worker) renders it at --spp with `aovs` lobes and
   light_groups.
3. Per pass: the image sum of the farm's layer over Cycles' (Cycles' direct and indirect passes
   times their colour pass, as its compositor rebuilds the image), and each side's passes
   summed against its own image (the farm's hold to float rounding; Cycles' to its own).
The two renderers differ in their models (the glTF spec's BRDF against the Principled BSDF:
bench/cycles_parity.py and docs/parity.md measure that on the image), so the ratios say whether
each pass holds the same light, not that the renderers agree to the noise.

    .venv/bin/python bench/passes_parity.py [combined ...] [--spp 256] [--reference-spp 1024]

Writes OUT/NAME.json and bench/results/passes_parity.json; prints a table.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
from cycles_parity import SUPPORT, generate_scenes, run_blender, worker_binary
from support.results import write_results

from renderfarm.cli.localfarm import LocalFarm
from renderfarm.client import Client
from renderfarm.domain.channels import LOBES
from renderfarm.infra.images import read_exr

# The farm's lobe layers and the Cycles passes (view layer pass names) each one is.
CYCLES_LOBES = {
    "diffuse_direct": ("Diffuse Direct", "Diffuse Color"),
    "diffuse_indirect": ("Diffuse Indirect", "Diffuse Color"),
    "glossy_direct": ("Glossy Direct", "Glossy Color"),
    "glossy_indirect": ("Glossy Indirect", "Glossy Color"),
    "transmission_direct": ("Transmission Direct", "Transmission Color"),
    "transmission_indirect": ("Transmission Indirect", "Transmission Color"),
    "emission": ("Emission", None),
    "background": ("Environment", None),
}


def exr_rgb(channels: dict, prefix: str) -> np.ndarray:
    return np.stack([channels[f"{prefix}{c}"] for c in "RGB"], -1).astype(np.float64)


def read_parts(path: Path) -> dict:
    """Every channel of every part of a multi-part EXR (Blender 5.0 writes a pass a part)."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    out, part = {}, 0
    while inp.seek_subimage(part, 0):
        pixels = inp.read_image(oiio.FLOAT)
        for i, name in enumerate(inp.spec().channelnames):
            out[name] = pixels[..., i]
        part += 1
    inp.close()
    return out


def cycles_layer(channels: dict, name: str) -> np.ndarray:
    """A pass of Cycles' multilayer EXR (its view layer's; "Combined" the image)."""
    (prefix,) = {c.rsplit(".", 2)[0] for c in channels if c.endswith(f".{name}.R")}
    return exr_rgb(channels, f"{prefix}.{name}.")


def render_cycles(scene: Path, env: dict | None, args, out: Path) -> tuple[dict, dict]:
    path = out / "cycles.exr"
    config = {"scene": str(scene), "width": args.width, "height": args.height,
              "max_depth": args.max_depth, "threads": args.threads, "environment": env,
              "renders": [{"spp": args.reference_spp, "seed": 1, "path": str(path)}],
              "passes": True}  # fmt: skip
    (out / "cycles.json").write_text(json.dumps(config))
    result = run_blender(SUPPORT / "cycles_render.py", [str(out / "cycles.json")], out,
                         f"Cycles rendering {scene}")  # fmt: skip
    return read_parts(path), result


def render_farm(scene: Path, env: dict | None, args, out: Path) -> tuple[dict, dict]:
    settings = {"width": args.width, "height": args.height, "max_spp": args.spp,
                "noise_threshold": 0, "max_depth": args.max_depth,
                "aovs": ["lobes", "light_groups"]}  # fmt: skip
    if env:
        settings |= {"environment": env["path"], "environment_intensity": env["intensity"],
                     "environment_rotation_deg": env["rotation_deg"]}  # fmt: skip
    with LocalFarm(workers=1, data_dir=out / "farm", threads=args.threads,
                   worker_args=None) as farm, Client(farm.url, timeout=120) as client:  # fmt: skip
        job = client.submit(str(scene), name=scene.stem, settings=settings)
        job = client.wait(job["id"], poll_s=0.5, timeout_s=24 * 3600)
        if job["state"] != "completed":
            sys.exit(f"the farm's job {job['id']} ended {job['state']}: {job.get('error')}")
        client.save_image(job["id"], out / "farm.exr", "exr")
    return read_exr(str(out / "farm.exr")), job


def ratio(a: float, b: float) -> float | None:
    return a / b if b > 1e-9 else None


def compare(farm: dict, cycles: dict, job: dict, groups: dict) -> dict:
    image = exr_rgb(farm, "")
    combined = cycles_layer(cycles, "Combined")
    figures: dict = {"image": {"farm": image.sum(), "cycles": combined.sum(),
                               "ratio": ratio(image.sum(), combined.sum())}}  # fmt: skip
    farm_total, cycles_total = np.zeros_like(image), np.zeros_like(image)
    for lobe, *_ in LOBES:
        ours = exr_rgb(farm, f"{lobe}.")
        light, colour = CYCLES_LOBES[lobe]
        theirs = cycles_layer(cycles, light)
        if colour:
            theirs = theirs * cycles_layer(cycles, colour)
        farm_total += ours
        cycles_total += theirs
        figures[lobe] = {"farm": ours.sum(), "cycles": theirs.sum(),
                         "ratio": ratio(ours.sum(), theirs.sum())}  # fmt: skip
    figures["lobes_sum_vs_image"] = {
        "farm": float(np.abs(farm_total - image).max() / max(image.max(), 1e-9)),
        "cycles": float(np.abs(cycles_total - combined).max() / max(combined.max(), 1e-9)),
    }
    farm_groups = json.loads(job["settings"]["light_groups"])
    group_total = np.zeros_like(image)
    for group in farm_groups:
        ours = exr_rgb(farm, f"light_group_{group}.")
        group_total += ours
        theirs = None
        if group in groups:
            theirs = cycles_layer(cycles, f"Combined_{group}")
        figures[f"light_group.{group}"] = {
            "farm": ours.sum(),
            "cycles": None if theirs is None else theirs.sum(),
            "ratio": None if theirs is None else ratio(ours.sum(), theirs.sum()),
        }
    figures["groups_sum_vs_image"] = float(
        np.abs(group_total - image).max() / max(image.max(), 1e-9)
    )
    return figures


def main() -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("scenes", nargs="*", default=["combined"])
    parser.add_argument("--spp", type=int, default=256)
    parser.add_argument("--reference-spp", type=int, default=1024)
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--height", type=int, default=120)
    parser.add_argument("--max-depth", type=int, default=8)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    worker_binary()  # exits naming what is missing
    out = args.out or Path(tempfile.mkdtemp(prefix="passes-parity-"))
    out.mkdir(parents=True, exist_ok=True)
    scenes = generate_scenes(args.scenes, out)
    results = {}
    for name in args.scenes:
        scratch = out / name
        scratch.mkdir(exist_ok=True)
        scene, env_map = Path(scenes[name]["scene"]), scenes[name].get("environment")
        env = env_map and {"path": env_map, "intensity": 1.0, "rotation_deg": 0.0}
        cycles, rendered = render_cycles(scene, env, args, scratch)
        farm, job = render_farm(scene, env, args, scratch)
        figures = compare(farm, cycles, job, rendered["light_groups"] or {})
        figures["settings"] = {"spp": args.spp, "reference_spp": args.reference_spp,
                               "width": args.width, "height": args.height,
                               "max_depth": args.max_depth}  # fmt: skip
        (scratch / f"{name}.json").write_text(json.dumps(figures, indent=2, default=float))
        results[name] = figures
        print(f"{name}: pass, farm sum, Cycles sum, farm / Cycles")
        for key, f in figures.items():
            if isinstance(f, dict) and "ratio" in f:
                r = "-" if f["ratio"] is None else f"{f['ratio']:.3f}"
                c = "-" if f["cycles"] is None else f"{f['cycles']:.1f}"
                print(f"  {key:32} {f['farm']:12.1f} {c:>12} {r:>7}")
        print(
            f"  each side's lobes against its image (max |diff| / max): "
            f"{figures['lobes_sum_vs_image']}; the farm's groups: "
            f"{figures['groups_sum_vs_image']:.2e}"
        )
    print(f"wrote {write_results('passes_parity', json.loads(json.dumps(results, default=float)))}")
    return results


if __name__ == "__main__":
    main()
