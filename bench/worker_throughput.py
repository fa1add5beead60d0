"""Worker render throughput: the C++ path tracer against Embree's raw ray rate.

Runs `renderfarm-worker bench` (worker/src/bench/bench.cpp), which renders the Cornell box, a
generated scene of at least 1M triangles and a generated scene of 144 Embree instances of one
mesh (both built in memory, never written to disk) at 1 and 2 threads, records the path
tracer's rays and replays them through bare rtcIntersect1 / rtcOccluded1 in the same process.
Prints samples/s, Mrays/s, the 1 -> 2 thread scaling and the ratio of the path tracer's ray
rate to the raw rate (targets: >= 0.6 and >= 1.8x), and writes
bench/results/worker_throughput.json.

Environment: RENDERFARM_WORKER (binary, default build/worker/renderfarm-worker),
BENCH_SPP / BENCH_SIZE / BENCH_THREADS to change the workload, BENCH_SCENES (a comma-separated
subset of cornell,mesh,instanced) to run only some of the scenes.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
TARGET_RATIO = 0.6
TARGET_SCALING = 1.8


def main() -> dict:
    binary = Path(os.environ.get("RENDERFARM_WORKER", ROOT / "build/worker/renderfarm-worker"))
    if not binary.exists():
        sys.exit(f"{binary} not found: build the worker first (make worker)")
    out = ROOT / "bench" / "results" / "worker_throughput.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    size = os.environ.get("BENCH_SIZE", "192")
    cmd = [
        str(binary),
        "bench",
        "--cornell",
        str(ROOT / "examples" / "cornell-box.gltf"),
        "--json",
        str(out),
        "--width",
        size,
        "--height",
        size,
        "--spp",
        os.environ.get("BENCH_SPP", "32"),
        "--threads",
        os.environ.get("BENCH_THREADS", "1,2"),
        "--scenes",
        os.environ.get("BENCH_SCENES", "cornell,mesh,instanced"),
    ]
    subprocess.run(cmd, check=True)
    doc = json.loads(out.read_text())
    summary = {}
    for scene in doc["scenes"]:
        by_threads = scene["threads"]
        counts = sorted(by_threads, key=int)
        ratios = [by_threads[t]["ray_rate_vs_raw"] for t in counts]
        scaling = by_threads[counts[-1]].get("scaling_vs_first")
        summary[scene["scene"]] = {"min_ratio": min(ratios), "scaling": scaling}
        verdict_ratio = "meets" if min(ratios) >= TARGET_RATIO else "below"
        line = (
            f"{scene['scene']:10} {scene['triangles']:>9,} triangles: ray rate "
            f"{min(ratios):.2f}-{max(ratios):.2f} of raw Embree ({verdict_ratio} {TARGET_RATIO})"
        )
        if scaling is not None:
            verdict_scaling = "meets" if scaling >= TARGET_SCALING else "below"
            line += f", scaling {scaling:.2f}x ({verdict_scaling} {TARGET_SCALING}x)"
        print(line)
    doc["summary"] = summary
    out.write_text(json.dumps(doc, indent=2) + "\n")
    print(f"wrote {out.relative_to(ROOT)}")
    return doc


if __name__ == "__main__":
    main()
