"""Which tile size? The same job (Cornell box 384x384, 32 spp, fixed work) at several tile sizes
on a local farm (2 workers, 1 thread each): total render time, time to the first full-frame
preview, and tasks per second the server handled. Small tiles cost per-task overhead (messages,
merges, scheduling); large tiles delay the first preview and leave workers idle at the end of a
job. Writes bench/results/tile_size.json; the default tile_size (64) is the one this picks.

    .venv/bin/python bench/tile_size.py
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

from support.results import write_results

from renderfarm.cli.localfarm import LocalFarm
from renderfarm.client import Client
from renderfarm.domain.tiling import batch_count

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "examples" / "cornell-box.gltf"
SIZE, SPP = 384, 32


def run(client: Client, tile: int) -> dict:
    settings = {"width": SIZE, "height": SIZE, "tile_size": tile, "max_spp": SPP}
    settings |= {"noise_threshold": 0, "seed": tile}
    started = time.perf_counter()
    job = client.submit(SCENE, settings=settings)
    preview = None
    for _ in range(200000):  # bounded polling (well over the longest expected job)
        job = client.get(job["id"])
        now = time.perf_counter() - started
        if preview is None and job["progress"]["samples_merged"] >= SIZE * SIZE:
            preview = now  # batch 0 (1 spp) of every tile goes first, so this is a full frame
        if job["state"] == "completed":
            break
        time.sleep(0.01)
    total = time.perf_counter() - started
    tasks = len(job["stops"]) * batch_count(SPP)  # every batch of every tile is rendered once
    return {"tile_size": tile, "total_s": total, "first_preview_s": preview,
            "tiles": len(job["stops"]), "tasks_per_s": tasks / total}  # fmt: skip


def main() -> dict:
    with tempfile.TemporaryDirectory(prefix="rf-bench-") as data:
        with LocalFarm(workers=2, data_dir=Path(data), threads=1) as farm, Client(farm.url) as c:
            for _ in range(600):
                if len(c.workers()) == 2:
                    break
                time.sleep(0.05)
            c.wait(c.submit(SCENE, settings={"width": 8, "height": 8, "max_spp": 1})["id"])
            rows = [run(c, tile) for tile in (16, 32, 64, 128)]
    for r in rows:
        print(
            f"tile {r['tile_size']:4}  total {r['total_s']:6.2f} s  first preview "
            f"{r['first_preview_s']:5.2f} s  tiles {r['tiles']:4}"
        )
    figures = {"resolution": SIZE, "spp": SPP, "runs": rows}
    write_results("tile_size", figures)
    return figures


if __name__ == "__main__":
    main()
