"""Merge throughput of the scheduler in-process: synthetic 64x64 tile results, no network.

Prints results/s, MB/s merged and merge latency p50/p99; writes bench/results/merge_throughput.json.
(bench/server_merge, through the real gRPC server, measures the whole path.)
"""

from __future__ import annotations

import time

import numpy as np
from support.results import write_results

from renderfarm.domain.jobspec import JobSettings
from renderfarm.domain.records import BatchResult
from renderfarm.domain.scheduler import Scheduler


def main(results_target: int = 20000) -> dict:
    settings = JobSettings(
        width=4096, height=4096, tile_size=64, noise_threshold=0, max_spp=1 << 16
    )
    sched = Scheduler()
    sched.add_job("bench", settings, "scene")
    sched.add_worker("w", 64)
    rng = np.random.default_rng(0)
    payload_rgb = rng.random(64 * 64 * 3) * 4
    payload_m2 = rng.random(64 * 64)
    latencies = []
    merged_bytes = 0
    started = time.perf_counter()
    while len(latencies) < results_target:
        for lease in sched.assign("w"):
            result = BatchResult(
                job_id=lease.job_id,
                tile_index=lease.tile_index,
                batch_index=lease.batch_index,
                sample_start=lease.sample_start,
                sample_count=lease.sample_count,
                rect=lease.rect,
                rgb_sum=payload_rgb * lease.sample_count,
                luminance_m2=payload_m2,
            )
            t0 = time.perf_counter()
            sched.complete(lease.task_id, result)
            latencies.append(time.perf_counter() - t0)
            merged_bytes += payload_rgb.nbytes + payload_m2.nbytes
    elapsed = time.perf_counter() - started
    lat = np.array(latencies)
    figures = {
        "results": len(latencies),
        "results_per_s": len(latencies) / elapsed,
        "merge_only_results_per_s": len(latencies) / lat.sum(),
        "mb_per_s": merged_bytes / elapsed / 1e6,
        "merge_latency_p50_ms": float(np.percentile(lat, 50) * 1e3),
        "merge_latency_p99_ms": float(np.percentile(lat, 99) * 1e3),
        "tiles": len(sched.jobs["bench"].tiles),
    }
    for key, value in figures.items():
        print(f"{key:28} {value:,.3f}" if isinstance(value, float) else f"{key:28} {value}")
    write_results("merge_throughput", figures)
    return figures


if __name__ == "__main__":
    main()
