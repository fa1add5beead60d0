"""Time from submit to the first full-frame preview of the Cornell box at 512x512.

A local farm (embedded PostgreSQL, server, 2 workers with 1 thread each on this 2-core
machine) is started and left idle; then the clock starts, the scene is uploaded and the job
submitted, and the job is polled until every tile has a merged batch (progress.tiles_previewed
== tiles_total); the clock stops when the client holds the PNG preview fetched then (what the
dashboard shows), so the figure includes producing a real image. The EXR's spp layer then
confirms (untimed) that every pixel has a sample. Repeated --runs times; writes
bench/results/first_preview.json (also the median time until all tiles merged, without the
PNG). Target: under 1 s.

    .venv/bin/python bench/first_preview.py [--runs 5]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

from support.results import write_results

from renderfarm.cli.localfarm import LocalFarm
from renderfarm.client import Client
from renderfarm.infra.images import read_exr

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "examples" / "cornell-box.gltf"
SIZE = 512


def first_preview_seconds(client: Client, scratch: Path, seed: int) -> tuple[float, float]:
    """(seconds until every tile has a merged batch, seconds until the client holds the PNG
    preview of that moment), both from just before the upload."""
    settings = {"width": SIZE, "height": SIZE, "max_spp": 64, "noise_threshold": 0, "seed": seed}
    started = time.perf_counter()
    job = client.submit(SCENE, settings=settings)
    for _ in range(20000):  # bounded: about 100 s of polling at most
        progress = client.get(job["id"])["progress"]
        if progress["tiles_previewed"] == progress["tiles_total"]:
            covered = time.perf_counter() - started
            png = client.image(job["id"], "png")
            elapsed = time.perf_counter() - started
            assert png.startswith(b"\x89PNG"), "the preview is a PNG"
            # Untimed check that the preview really is full-frame: every pixel has a sample.
            exr = scratch / "preview.exr"
            exr.write_bytes(client.image(job["id"], "exr"))
            assert read_exr(str(exr))["spp"].min() >= 1, "a pixel of the preview has no sample"
            client.cancel(job["id"])
            return covered, elapsed
        time.sleep(0.005)
    raise TimeoutError("no full-frame preview")


def main() -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="rf-bench-") as data:
        with LocalFarm(workers=2, data_dir=Path(data), threads=1) as farm, Client(farm.url) as c:
            for _ in range(600):
                if len(c.workers()) == 2:
                    break
                time.sleep(0.05)
            c.submit(SCENE, settings={"width": 8, "height": 8, "max_spp": 1})  # warm caches
            time.sleep(1.0)
            runs = [first_preview_seconds(c, Path(data), seed) for seed in range(args.runs)]
    times = [png for _, png in runs]
    covered = [tiles for tiles, _ in runs]
    figures = {
        "first_preview_s_median": statistics.median(times),
        "first_preview_s_min": min(times),
        "first_preview_s_max": max(times),
        "runs": times,
        "all_tiles_merged_s_median": statistics.median(covered),
        "resolution": SIZE,
        "workers": 2,
        "threads_per_worker": 1,
        "target_s": 1.0,
    }
    for key, value in figures.items():
        print(f"{key:24} {value}")
    write_results("first_preview", figures)
    return figures


if __name__ == "__main__":
    main()
