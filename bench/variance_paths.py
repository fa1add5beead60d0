"""Where a scene's noise comes from, by path type (#38): the variance of the farm's lobe layers.

For each scene (a parity scene of bench/support/parity_scenes.py by name; default the realistic
suite, REALISTIC: realistic_floor, interior_window, product_hdr, exported by Blender's glTF
exporter as bench/cycles_parity.py does):
1. A local farm (embedded PostgreSQL, one worker) renders it --renders times (seeds 1..K) at
   --spp with `aovs` lobes and noise_threshold 0, so every pixel gets exactly --spp samples;
   each --setting KEY=VALUE is merged into the job's settings (a lever such as a `guiding`
   switch, to compare a scene before and after it).
2. Per lobe layer (renderfarm.domain.channels LOBES: they sum to the image) and for the image:
   the variance of one render's pixel luminance (0.2126 R + 0.7152 G + 0.0722 B), the unbiased
   sample variance across the K renders, averaged over the pixels; each lobe's share of the
   lobes' summed variances and of the image's; and the covariance remainder, the image's
   variance minus the lobes' summed variances (zero when the lobes' noise is uncorrelated), with
   its standard error from the pixels' spread (conservative).
3. The same for the issue's path types, each the variance of its lobes' summed layer: direct
   (diffuse_direct, glossy_direct, transmission_direct, emission, background), indirect diffuse
   (diffuse_indirect), glossy (glossy_direct, glossy_indirect), through glass
   (transmission_direct, transmission_indirect). glossy_direct is both direct and glossy, so
   the path types' shares need not sum to 1.
4. Where in the image: the share of the image's variance in its top 1% of pixels (by their
   variance; with few renders the pick leans to pixels whose estimate came out high) with the
   lobes' shares there, and in each block of a --grid x --grid grid with its largest lobe.

    .venv/bin/python bench/variance_paths.py [realistic_floor ...] [--spp 64] [--renders 4]
    .venv/bin/python bench/variance_paths.py product_hdr --setting guiding=true --out /tmp/var

Writes OUT/NAME.json per scene and bench/results/variance_paths.json; prints a table per scene
and a Markdown summary (one row per scene, as docs/parity.md has it).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from cycles_parity import generate_scenes, pixel_variance, regions, worker_binary
from support.parity_scenes import REALISTIC, SCENES
from support.results import write_results

from renderfarm.cli.localfarm import LocalFarm
from renderfarm.client import ApiError, Client
from renderfarm.domain.channels import LOBES
from renderfarm.infra.images import read_exr

LUMA = np.array([0.2126, 0.7152, 0.0722])
LOBE_NAMES = tuple(name for name, *_ in LOBES)
# Short names of the lobes in the table's block grid.
SHORT = {"diffuse_direct": "dd", "diffuse_indirect": "di", "glossy_direct": "gd",
         "glossy_indirect": "gi", "transmission_direct": "td", "transmission_indirect": "ti",
         "emission": "em", "background": "bg"}  # fmt: skip
# The issue's path types and the lobes each one sums (they overlap in glossy_direct).
PATH_TYPES = {
    "direct": ("diffuse_direct", "glossy_direct", "transmission_direct", "emission", "background"),
    "indirect_diffuse": ("diffuse_indirect",),
    "glossy": ("glossy_direct", "glossy_indirect"),
    "through_glass": ("transmission_direct", "transmission_indirect"),
}
TOP_FRACTION = 0.01


def setting(text: str) -> tuple[str, object]:
    """KEY=VALUE of --setting: the value JSON-decoded when it parses, else the string."""
    key, sep, value = text.partition("=")
    if not sep or not key.strip():
        raise argparse.ArgumentTypeError(f"--setting {text!r}: expected KEY=VALUE")
    try:
        return key.strip(), json.loads(value)
    except json.JSONDecodeError:
        return key.strip(), value


def luminance(channels: dict, prefix: str) -> np.ndarray:
    return np.stack([channels[f"{prefix}{c}"] for c in "RGB"], -1).astype(np.float64) @ LUMA


def render(client: Client, scene: Path, settings: dict, seed: int, path: Path) -> dict:
    """One render of the scene by the farm: "layers" ({"image": its luminance, lobe: the lobe's
    luminance, ...}), "seconds" (submit to completed) and "rgb_gap" (max |lobes' RGB sum -
    image| / the image's max)."""
    start = time.perf_counter()
    try:
        job = client.submit(
            str(scene), name=f"{scene.stem}-{seed}", settings={**settings, "seed": seed}
        )
    except ApiError as e:  # a --setting the farm does not know, or a bad value
        sys.exit(f"the farm refused the job: {e}")
    job = client.wait(job["id"], poll_s=0.5, timeout_s=24 * 3600)
    seconds = time.perf_counter() - start
    if job["state"] != "completed":
        sys.exit(f"the farm's job {job['id']} ended {job['state']}: {job.get('error')}")
    client.save_image(job["id"], path, "exr")
    channels = read_exr(str(path))
    out = {"image": luminance(channels, "")}
    image_rgb = np.stack([channels[c] for c in "RGB"], -1).astype(np.float64)
    total = np.zeros_like(image_rgb)
    for lobe in LOBE_NAMES:
        total += np.stack([channels[f"{lobe}.{c}"] for c in "RGB"], -1)
        out[lobe] = luminance(channels, f"{lobe}.")
    gap = float(np.abs(total - image_rgb).max() / max(float(image_rgb.max()), 1e-12))
    return {"layers": out, "seconds": seconds, "rgb_gap": gap}


def share(part: float, whole: float) -> float | None:
    return float(part / whole) if whole > 0 else None


def analyse(renders: list[dict], grid: int) -> dict:
    """The figures of one scene from its K renders (docstring, steps 2 to 4)."""
    stacks = {name: np.stack([r["layers"][name] for r in renders])
              for name in ("image", *LOBE_NAMES)}  # fmt: skip
    var = {name: pixel_variance(s) for name, s in stacks.items()}
    n = var["image"].size
    image_var = float(var["image"].mean())
    lobe_var = {lobe: float(var[lobe].mean()) for lobe in LOBE_NAMES}
    lobes_sum = sum(lobe_var.values())
    remainder = var["image"] - sum(var[lobe] for lobe in LOBE_NAMES)
    figures: dict = {
        "image": {"mean": float(stacks["image"].mean()), "variance": image_var,
                  "relative_variance": share(image_var, float(stacks["image"].mean()) ** 2)},
        "lobes": {
            lobe: {"mean": float(stacks[lobe].mean()), "variance": lobe_var[lobe],
                   "share_of_lobes": share(lobe_var[lobe], lobes_sum),
                   "share_of_image": share(lobe_var[lobe], image_var)}
            for lobe in LOBE_NAMES
        },
        "lobes_summed_variance": lobes_sum,
        "covariance_remainder": {
            "variance": float(remainder.mean()),
            "se": float(remainder.std(ddof=1) / math.sqrt(n)),
            "share_of_image": share(float(remainder.mean()), image_var),
        },
        "lobes_sum_vs_image_rgb": max(r["rgb_gap"] for r in renders),
    }  # fmt: skip
    figures["path_types"] = {}
    for kind, lobes in PATH_TYPES.items():
        summed = sum(stacks[lobe] for lobe in lobes)
        v = float(pixel_variance(summed).mean())
        figures["path_types"][kind] = {
            "lobes": list(lobes), "mean": float(summed.mean()), "variance": v,
            "share_of_image": share(v, image_var),
        }  # fmt: skip
    # The top 1% of pixels by the image's variance, and the lobes' shares of their variance.
    flat = var["image"].ravel()
    count = max(1, round(TOP_FRACTION * n))
    top = np.argpartition(flat, n - count)[n - count :]
    top_lobes = {lobe: float(var[lobe].ravel()[top].sum()) for lobe in LOBE_NAMES}
    top_sum = sum(top_lobes.values())
    figures["top_pixels"] = {
        "fraction": TOP_FRACTION, "pixels": count,
        "share_of_image": share(float(flat[top].sum()), float(flat.sum())),
        "lobes_share": {lobe: share(v, top_sum) for lobe, v in top_lobes.items()},
    }  # fmt: skip
    figures["blocks"] = []
    h, w = var["image"].shape
    for name, (x0, y0, x1, y1) in regions(w, h, grid, [])[1:]:  # [0]: the whole image
        in_block = {lobe: float(var[lobe][y0:y1, x0:x1].sum()) for lobe in LOBE_NAMES}
        largest = max(in_block, key=in_block.get)
        figures["blocks"].append({
            "block": name, "rect": [x0, y0, x1, y1],
            "share_of_image": share(float(var["image"][y0:y1, x0:x1].sum()), float(flat.sum())),
            "largest_lobe": largest,
            "largest_lobe_share": share(in_block[largest], sum(in_block.values())),
        })  # fmt: skip
    return figures


def pct(x: float | None, spec: str = "6.1f") -> str:
    return "-" if x is None else format(100 * x, spec)


def print_scene(name: str, f: dict, grid: int) -> None:
    s = f["settings"]
    extra = f" {json.dumps(s['extra'])}" if s["extra"] else ""
    print(f"{name}: {s['renders']} renders of {s['spp']} spp, {s['width']}x{s['height']}, "
          f"max_depth {s['max_depth']}{extra}; {np.mean(f['seconds']):.1f} s/render; variance "
          "of one render's pixel luminance, mean over pixels")  # fmt: skip
    head = f"  {'layer':22} {'mean':>9} {'variance':>10} {'% lobes':>8} {'% image':>8}"
    print(head)
    print("  " + "-" * (len(head) - 2))
    for lobe, r in f["lobes"].items():
        print(f"  {lobe:22} {r['mean']:9.4f} {r['variance']:10.3e} "
              f"{pct(r['share_of_lobes']):>8} {pct(r['share_of_image']):>8}")  # fmt: skip
    total, image, rem = f["lobes_summed_variance"], f["image"], f["covariance_remainder"]
    print(f"  {'lobes summed':22} {'':9} {total:10.3e} {'100.0':>8} "
          f"{pct(share(total, image['variance'])):>8}")  # fmt: skip
    print(f"  {'image':22} {image['mean']:9.4f} {image['variance']:10.3e} {'':8} {'100.0':>8}")
    print(
        f"  {'covariance remainder':22} {'':9} {rem['variance']:10.3e} {'':8} "
        f"{pct(rem['share_of_image']):>8}  (+- {rem['se']:.2e}, image - lobes summed)"
    )
    print("  path types (variance of the lobes' summed layer; glossy_direct is in two):")
    for kind, r in f["path_types"].items():
        print(f"  {kind:22} {r['mean']:9.4f} {r['variance']:10.3e} {'':8} "
              f"{pct(r['share_of_image']):>8}")  # fmt: skip
    top = f["top_pixels"]
    lobes = sorted(top["lobes_share"].items(), key=lambda kv: -(kv[1] or 0))[:3]
    print(f"  top {100 * top['fraction']:g}% of pixels ({top['pixels']}): "
          f"{pct(top['share_of_image'], '.1f')}% of the image's variance; there "
          + ", ".join(f"{lobe} {pct(v, '.0f')}%" for lobe, v in lobes))  # fmt: skip
    print(f"  blocks ({grid}x{grid}, rows from the top): % of the image's variance, largest lobe")
    for r in range(grid):
        row = f["blocks"][r * grid : (r + 1) * grid]
        cells = (f"{pct(b['share_of_image'], '5.1f')} {SHORT[b['largest_lobe']]}" for b in row)
        print("    " + "  ".join(cells))
    print(
        f"  ({', '.join(f'{v} {k}' for k, v in SHORT.items())}; the lobes' RGB sum against "
        f"the image: max |diff| / max {f['lobes_sum_vs_image_rgb']:.1e})"
    )


def print_summary(results: dict) -> None:
    """One Markdown row per scene: the image's variance, the path types' and the remainder's
    shares of it, the top 1%'s and the largest block's."""
    kinds = " | ".join(k.replace("_", " ") for k in PATH_TYPES)
    print(f"| scene | image variance | {kinds} | remainder | top 1% px | largest block |")
    print("|---|---:|" + "---:|" * len(PATH_TYPES) + "---:|---:|---|")
    for name, f in results.items():
        shares = " | ".join(f"{pct(r['share_of_image'], '.1f')}%"
                            for r in f["path_types"].values())  # fmt: skip
        block = max(f["blocks"], key=lambda b: b["share_of_image"] or 0)
        rem, top = f["covariance_remainder"], f["top_pixels"]
        print(f"| `{name}` | {f['image']['variance']:.3g} | {shares} | "
              f"{pct(rem['share_of_image'], '.1f')}% | {pct(top['share_of_image'], '.1f')}% | "
              f"{block['block']} {pct(block['share_of_image'], '.0f')}% "
              f"({block['largest_lobe']}) |")  # fmt: skip


def main() -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("scenes", nargs="*", default=list(REALISTIC),
                        help=f"parity scenes (default: {', '.join(REALISTIC)})")  # fmt: skip
    parser.add_argument("--spp", type=int, default=64)
    parser.add_argument("--renders", type=int, default=4, help="renders per scene, seeds 1..K")
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--max-depth", type=int, default=13)
    parser.add_argument("--grid", type=int, default=4, help="the image's blocks: N x N (N >= 2)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument(
        "--setting",
        type=setting,
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a further job setting (repeatable; VALUE JSON-decoded when it parses)",
    )
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    for key in ("spp", "width", "height", "max_depth", "grid", "threads"):
        if getattr(args, key) < 1:
            parser.error(f"--{key.replace('_', '-')} must be >= 1")
    if args.renders < 2:
        parser.error("--renders must be >= 2 (the variance is estimated across renders)")
    if args.grid < 2:
        parser.error("--grid must be >= 2 (the image split into blocks)")
    unknown = [n for n in args.scenes if n not in SCENES]
    if unknown:
        parser.error(f"not parity scenes: {', '.join(unknown)} (known: {', '.join(SCENES)})")
    extra = dict(args.setting)
    worker_binary()  # exits naming what is missing
    out = (args.out or Path(tempfile.mkdtemp(prefix="variance-paths-"))).resolve()
    out.mkdir(parents=True, exist_ok=True)
    scenes = generate_scenes(args.scenes, out)
    results = {}
    with (
        LocalFarm(workers=1, data_dir=out / "farm", threads=args.threads) as farm,
        Client(farm.url, timeout=120) as client,
    ):
        for name in args.scenes:
            scratch = out / name
            scratch.mkdir(exist_ok=True)
            scene, env = Path(scenes[name]["scene"]), scenes[name].get("environment")
            settings = {"width": args.width, "height": args.height, "max_spp": args.spp,
                        "noise_threshold": 0, "max_depth": args.max_depth,
                        "aovs": ["lobes"]}  # fmt: skip
            if env:
                settings |= {"environment": env, "environment_intensity": 1.0,
                             "environment_rotation_deg": 0.0}  # fmt: skip
            settings |= extra
            renders = []
            for k in range(1, args.renders + 1):
                renders.append(render(client, scene, settings, k, scratch / f"farm-{k}.exr"))
                print(f"{name}: render {k}/{args.renders} in {renders[-1]['seconds']:.1f} s",
                      file=sys.stderr)  # fmt: skip
            figures = {
                "scene": name,
                "file": str(scene),
                "environment": env,
                "settings": {"spp": args.spp, "renders": args.renders, "width": args.width,
                             "height": args.height, "max_depth": args.max_depth,
                             "grid": args.grid, "threads": args.threads, "extra": extra},
                "seconds": [r["seconds"] for r in renders],
                **analyse(renders, args.grid),
            }  # fmt: skip
            (out / f"{name}.json").write_text(json.dumps(figures, indent=2) + "\n")
            results[name] = figures
            print_scene(name, figures, args.grid)
            print()
    print_summary(results)
    print(f"wrote {write_results('variance_paths', results)} and {out}/NAME.json")
    return results


if __name__ == "__main__":
    main()
