"""Tiles or chunks for a sequence? The same animation job (examples/make_hinged_box.py, 12
frames, 64 spp, fixed work) at several frame sizes, each with its frames cut into 32-pixel
tiles, into the default 64-pixel tiles, and sent whole as one tile per frame (a "chunk":
tile_size set to the frame's longer side), on a local farm (2 workers, 1 thread each): total
time, time until the first frame is done, and tasks per second the server handled. A tile
costs per-task overhead (messages, merges, scheduling) and, with many frames in flight, buys
no parallelism a chunk lacks; but its noise stops it on its own, and a chunk must wait for
its noisiest pixels. Writes bench/results/frame_chunks.json; docs/animation.md ("Tiles or
chunks") states the rule these figures give.

    .venv/bin/python bench/frame_chunks.py
    BENCH_SIZES=64x48,128x96 BENCH_FRAMES=1-24 .venv/bin/python bench/frame_chunks.py
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from support.results import write_results

from renderfarm.cli.localfarm import LocalFarm
from renderfarm.client import Client
from renderfarm.domain.frames import parse_frames
from renderfarm.domain.tiling import batch_count

ROOT = Path(__file__).resolve().parents[1]
SPP = int(os.environ.get("BENCH_SPP", "64"))
FRAMES = os.environ.get("BENCH_FRAMES", "1-12")
SIZES = [
    tuple(int(v) for v in size.split("x"))
    for size in os.environ.get("BENCH_SIZES", "64x48,128x96,256x192,384x288").split(",")
]


def run(client: Client, scene: Path, width: int, height: int, tile: int) -> dict:
    settings = {"width": width, "height": height, "tile_size": tile, "max_spp": SPP}
    settings |= {"noise_threshold": 0, "seed": 3, "frames": FRAMES}
    started = time.perf_counter()
    job = client.submit(scene, settings=settings)
    first_frame = None
    for _ in range(200000):  # bounded polling (well over the longest expected job)
        job = client.get(job["id"])
        now = time.perf_counter() - started
        if first_frame is None and job["progress"]["frames_done"] >= 1:
            first_frame = now
        if job["state"] == "completed":
            break
        time.sleep(0.01)
    total = time.perf_counter() - started
    tiles = job["progress"]["tiles_total"]
    tasks = tiles * batch_count(SPP)  # every batch of every tile is rendered once
    return {"width": width, "height": height, "tile_size": tile,
            "chunk": tile >= max(width, height), "tiles": tiles, "total_s": total,
            "first_frame_s": first_frame, "tasks_per_s": tasks / total,
            "megasamples_per_s": width * height * SPP * len(parse_frames(FRAMES, 10**6))
            / total / 1e6}  # fmt: skip


def main() -> dict:
    with tempfile.TemporaryDirectory(prefix="rf-bench-") as data:
        scene = Path(data) / "hinged-box.glb"
        script = ROOT / "examples" / "make_hinged_box.py"
        subprocess.run([sys.executable, str(script), "-o", str(scene)], check=True,
                       capture_output=True)  # fmt: skip
        with LocalFarm(workers=2, data_dir=Path(data) / "farm", threads=1) as farm:
            with Client(farm.url) as c:
                for _ in range(600):
                    if len(c.workers()) == 2:
                        break
                    time.sleep(0.05)
                c.wait(c.submit(scene, settings={"width": 8, "height": 8, "max_spp": 1})["id"])
                rows = []
                for width, height in SIZES:
                    for tile in sorted({32, 64, max(width, height)}):
                        if tile > max(width, height):
                            continue
                        rows.append(run(c, scene, width, height, tile))
                        r = rows[-1]
                        kind = " (chunk)" if r["chunk"] else ""
                        print(
                            f"{width:4}x{height:<4} tile {tile:4}{kind:8}"
                            f"  tiles {r['tiles']:5}  total {r['total_s']:6.2f} s  first frame "
                            f"{r['first_frame_s']:6.2f} s  {r['megasamples_per_s']:5.2f} Ms/s  "
                            f"{r['tasks_per_s']:6.0f} tasks/s",
                            flush=True,
                        )
    figures = {"frames": FRAMES, "spp": SPP, "workers": 2, "threads": 1, "runs": rows}
    write_results("frame_chunks", figures)
    return figures


if __name__ == "__main__":
    main()
