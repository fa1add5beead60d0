"""Adaptive stopping against uniform sampling at equal cost, on three scenes.

- A shelter in the sun (bench/support/shelter_scene.py): a bright, easy region (sunlit ground)
  and a dark, hard one (the shelter's inside and shadow, lit by bounced light), the scene the
  adaptivity claim is about. 160x160.
- The Cornell box: a closed interior where every tile is hard. 128x128.
- A box on a floor under a sky (bench/support/sky_scene.py): half the frame is sky, converged
  at once, but also nearly free to sample. 128x128.
On each:
1. A reference at 8192 (shelter), 4096 (Cornell box) or 16384 spp (sky).
2. An adaptive job (noise_threshold T): each tile stops when its error estimate is below T.
3. A uniform job with the same total number of samples, spread evenly (max_spp = the adaptive
   job's mean spp, rounded down, so the uniform job never gets more samples).
4. A uniform job at equal render time: its spp scaled by the ratio of the two render times
   (adaptive jobs spend samples where they cost more or less than the average).
Both images are compared with the reference: the relative MSE (squared error over
max(reference, 0.01)^2, what the noise threshold controls), the plain RGB MSE, the display MSE
(of the sRGB-encoded image as the PNG preview shows it, in 8-bit levels squared), and the 95th
percentile and maximum of the tiles' errors. Render time is the server's elapsed_s of the job
(first lease to last merge). Writes
bench/results/adaptive_efficiency.json.

What to expect: stopping every tile at the same error gives tile t about sigma_t^2 / T^2
samples. When every tile needs more than min_spp (the Cornell box), that has the same expected
mean squared error at equal cost as spreading the samples evenly, times
mean(sigma^2) mean(cost) / mean(sigma^2 cost) over the tiles: no gain unless noisy tiles are the
cheap ones; the gain there is an even image (a lower worst-tile error). Where tiles are easy
they stop at min_spp with an error far below T, and the time uniform sampling spends on them
goes to the hard tiles: the shelter. Under the sky, the easy tiles cost almost nothing, so
there is little time to win back. (The allocation that minimises the mean squared error gives
tile t samples in proportion to sigma_t / sqrt(cost_t), Neyman allocation; equal-error stopping
is what the noise threshold promises instead.)

    .venv/bin/python bench/adaptive_efficiency.py [--shelter-threshold 0.05]
        [--threshold 0.05] [--sky-threshold 0.02] [--adaptive tile|pixel|pixel_mse]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
from support import shelter_scene, sky_scene
from support.results import write_results

from renderfarm.cli.localfarm import LocalFarm
from renderfarm.client import Client
from renderfarm.domain.merge import DARK_FLOOR
from renderfarm.infra.images import read_exr, srgb_encode

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "examples" / "cornell-box.gltf"
LUMA = np.array([0.2126, 0.7152, 0.0722])


def render(
    client: Client, scratch: Path, scene: Path, name: str, size: int, **settings
) -> tuple[dict, dict, float]:
    base = {"width": size, "height": size, "tile_size": 32, "seed": 3}
    job = client.submit(scene, settings={**base, **settings}, name=name)
    job = client.wait(job["id"], poll_s=0.1, timeout_s=3600)
    # The server's render time (first lease to last merge): no upload or polling in it.
    elapsed = job["progress"]["elapsed_s"]
    path = scratch / f"{name}.exr"
    path.write_bytes(client.image(job["id"], "exr"))
    return job, read_exr(str(path)), elapsed


def rgb(ch: dict) -> np.ndarray:
    return np.stack([ch["R"], ch["G"], ch["B"]], axis=-1).astype(np.float64)


def errors(ch: dict, ref: dict) -> dict[str, float]:
    """Relative MSE, RGB MSE, display MSE, and the 95th percentile and maximum of the tiles'
    RMS relative errors (32x32 tiles): adaptive stopping evens these out."""
    a, r = rgb(ch), rgb(ref)
    # Luminance relative error, the quantity the noise threshold controls (docs/architecture.md).
    rel = (((a - r) @ LUMA) / np.maximum(r @ LUMA, DARK_FLOOR)) ** 2
    size = rel.shape[0]
    tiles = rel.reshape(size // 32, 32, size // 32, 32).mean(axis=(1, 3))
    tile_err = np.sqrt(tiles).ravel()
    return {
        "relative_mse": float(rel.mean()),
        "rgb_mse": float(np.mean((a - r) ** 2)),
        # The image as the PNG preview shows it (sRGB-encoded, clipped to [0, 1]), in 8-bit
        # levels squared: the error a viewer sees.
        "display_mse": float(np.mean(((srgb_encode(a) - srgb_encode(r)) * 255.0) ** 2)),
        "tile_error_p95": float(np.percentile(tile_err, 95)),
        "tile_error_max": float(tile_err.max()),
    }


def compare(
    client: Client,
    scratch: Path,
    label: str,
    scene: Path,
    threshold: float,
    ref_spp: int,
    size: int = 128,
    adaptive: str = "tile",
    **extra,
):
    """Reference, adaptive and uniform renders of one scene; the figures of the comparison."""
    _, ref, _ = render(client, scratch, scene, f"{label}-reference", size, noise_threshold=0,
                       max_spp=ref_spp, **extra)  # fmt: skip
    adaptive, a_img, a_time = render(
        client,
        scratch,
        scene,
        f"{label}-adaptive",
        size,
        noise_threshold=threshold,
        max_spp=4096,
        adaptive=adaptive,
        **extra,
    )
    spp = int(adaptive["progress"]["mean_spp"])
    _, u_img, u_time = render(
        client, scratch, scene, f"{label}-uniform", size, noise_threshold=0, max_spp=spp, **extra
    )
    # Uniform again with the spp scaled to the adaptive job's render time: the comparison at
    # equal time (adaptive tiles spend their samples where a sample costs more or less).
    spp_t = max(1, round(spp * a_time / u_time))
    _, t_img, t_time = render(
        client,
        scratch,
        scene,
        f"{label}-uniform-equal-time",
        size,
        noise_threshold=0,
        max_spp=spp_t,
        **extra,
    )
    a, u, t = errors(a_img, ref), errors(u_img, ref), errors(t_img, ref)
    figures = {
        "size": size,
        "threshold": threshold,
        "reference_spp": ref_spp,
        "adaptive_mean_spp": adaptive["progress"]["mean_spp"],
        "uniform_spp": spp,
        "adaptive_seconds": a_time,
        "uniform_seconds": u_time,
        "equal_time_uniform_spp": spp_t,
        "equal_time_uniform_seconds": t_time,
        # Efficiency = 1 / (error x time): the gain of adaptive over uniform.
        "adaptive_efficiency_gain": (u["relative_mse"] * u_time) / (a["relative_mse"] * a_time),
    }
    for key in a:
        figures[f"adaptive_{key}"] = a[key]
        figures[f"uniform_{key}"] = u[key]
        figures[f"equal_time_uniform_{key}"] = t[key]
    for key in ("relative_mse", "rgb_mse", "display_mse"):
        # Above 1: adaptive stopping has the lower error.
        figures[f"{key}_ratio_uniform_over_adaptive"] = u[key] / a[key]
        figures[f"equal_time_{key}_ratio_uniform_over_adaptive"] = t[key] / a[key]
    return figures


def main() -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shelter-threshold", type=float, default=0.05, help="shelter")
    parser.add_argument("--threshold", type=float, default=0.05, help="Cornell box")
    parser.add_argument("--sky-threshold", type=float, default=0.02, help="box under a sky")
    parser.add_argument(
        "--adaptive",
        choices=("tile", "pixel", "pixel_mse"),
        default="tile",
        help="the adaptive jobs' setting adaptive: per tile (default), per pixel or per pixel "
        "by the least MSE; pixel writes adaptive_efficiency_pixel.json, pixel_mse "
        "adaptive_efficiency_pixel_mse.json",
    )
    args = parser.parse_args()
    mode = {"adaptive": args.adaptive}
    figures = {}
    with tempfile.TemporaryDirectory(prefix="rf-bench-") as data:
        scratch = Path(data)
        sky_gltf, sky_hdr = sky_scene.write(scratch / "sky")
        shelter = shelter_scene.write(scratch / "shelter")
        with LocalFarm(workers=2, data_dir=scratch / "farm", threads=1) as farm:
            with Client(farm.url, timeout=60) as client:
                figures["shelter"] = compare(
                    client, scratch, "shelter", shelter, args.shelter_threshold, ref_spp=8192,
                    size=160, **mode,
                )  # fmt: skip
                figures["cornell"] = compare(
                    client, scratch, "cornell", SCENE, args.threshold, ref_spp=4096, **mode
                )
                # The sky scene is cheap per sample: a tighter threshold and a deeper reference
                # (the reference's own noise must stay well below the threshold).
                figures["sky_box"] = compare(
                    client,
                    scratch,
                    "sky",
                    sky_gltf,
                    args.sky_threshold,
                    ref_spp=16384,
                    environment=str(sky_hdr),
                    **mode,
                )
    for scene, values in figures.items():
        print(scene)
        for key, value in values.items():
            print(f"  {key:42} {value:.6g}")
    name = "adaptive_efficiency" + ("" if args.adaptive == "tile" else f"_{args.adaptive}")
    write_results(name, figures)
    return figures


if __name__ == "__main__":
    main()
