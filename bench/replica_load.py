"""A simulated fleet against a farm of 1 and of 2 servers over one PostgreSQL (#39).

Each synthetic worker (bench/server_merge.py's: a pre-built 64x64 result shaped like the C++
worker's for every task, ready after a render time drawn from 0.5 to 1.5 x --render-s, 0.25 s by
default: a 64-spp Cornell box tile on one core of this machine) opens one stream to every
server, as `renderfarm-worker connect --server A,B` does, with --cores tasks in flight on each
(64 by default: a node of 64 cores). Results leave as the C++ worker's ResultPacker sends
them: a message at most every --result-interval-ms (50 by default, the worker's default; sooner
when 64 results fill it) with every result ready by then (--no-pack: one message per result,
as workers did before packed messages). The fleet offers far more results than a server
merges, so the figures are the servers' capacity. One job per server (the servers share the
jobs, so each owns one). Over the measured window it prints, per
farm size: results merged per second (all servers), the servers' CPU per result (user + system
time of every server process over the results they merged), and PostgreSQL's cost per result
(transactions committed and rows written, from pg_stat_database, and the CPU of its
processes). CPU per result is what sizes a farm (docs/operations.md, "Scaling"): results/s
alone depends on what else shares this machine's cores (here the load generator and
PostgreSQL do). Writes bench/results/replica_load.json.

    .venv/bin/python bench/replica_load.py [--workers 1000] [--replicas 1,2] [--seconds 10]
        [--render-s 0.25] [--cores 64] [--result-interval-ms 50] [--no-pack]
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
import tempfile
import time
from multiprocessing import Process, Value
from pathlib import Path

import psycopg
from server_merge import TILE, pin_process, scrape, synthetic_worker
from support.results import write_results

from renderfarm.cli.localfarm import LocalFarm
from renderfarm.client import Client
from renderfarm.infra.embedded_db import EmbeddedPostgres

ROOT = Path(__file__).resolve().parents[1]
MERGED = 'renderfarm_tasks_completed_total{outcome="merged"}'
CLOCK_TICKS = os.sysconf("SC_CLK_TCK")


def cpu_seconds(pid: int) -> float:
    """User + system time of a process (all its threads) so far."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rpartition(")")[2].split()
    return (int(fields[11]) + int(fields[12])) / CLOCK_TICKS


def postgres_pids(pgdata: Path) -> list[int]:
    postmaster = int((pgdata / "postmaster.pid").read_text().split()[0])
    found = [postmaster]
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rpartition(")")[2].split()
            except OSError:
                continue
            if int(fields[1]) == postmaster:
                found.append(int(entry.name))
    return found


def total_cpu(pids: list[int]) -> float:
    total = 0.0
    for pid in pids:
        try:
            total += cpu_seconds(pid)
        except OSError:
            pass  # a backend that ended
    return total


def database_writes(url: str) -> tuple[int, int]:
    """(transactions committed, rows inserted + updated + deleted) of the farm's database."""
    with psycopg.connect(url) as conn:
        row = conn.execute(
            "SELECT xact_commit, tup_inserted + tup_updated + tup_deleted"
            " FROM pg_stat_database WHERE datname = current_database()"
        ).fetchone()
    return int(row[0]), int(row[1])


def fleet(
    addresses: list[str],
    workers: int,
    seconds: float,
    sent,
    messages,
    cpus: set[int],
    packed: bool,
    render_s: float,
    cores: int,
    interval_s: float,
) -> None:
    """The load generator: `workers` synthetic workers, each with a stream to every server."""
    os.sched_setaffinity(0, cpus)
    stop_at = time.monotonic() + seconds

    async def run():
        streams = [
            synthetic_worker(
                address, f"fleet-{i}@{address}", cores, stop_at, packed, render_s, interval_s
            )  # fmt: skip
            for i in range(workers)
            for address in addresses
        ]
        counts = await asyncio.gather(*streams)
        sent.value = sum(c[0] for c in counts)
        messages.value = sum(c[2] for c in counts)

    asyncio.run(run())


def measure(
    replicas: int,
    workers: int,
    seconds: float,
    cache_mb: int,
    data: Path,
    packed: bool,
    render_s: float,
    cores: int,
    interval_s: float,
) -> dict:
    db = EmbeddedPostgres(data / "db")
    url = db.start()
    farms: list[LocalFarm] = []
    try:
        env = {
            "RENDERFARM_DATABASE_URL": url,
            "RENDERFARM_TILE_CACHE_MB": str(cache_mb),
            **{k: v for k, v in os.environ.items() if k.startswith("RENDERFARM_")},
        }
        for i in range(replicas):
            farm = LocalFarm(workers=0, data_dir=data / f"server-{i}",
                             env={**env, "RENDERFARM_REPLICA_ID": f"server-{i}"})  # fmt: skip
            farm.start()
            farms.append(farm)
        cpus = os.cpu_count() or 1
        for i, farm in enumerate(farms):
            pin_process(farm.server.pid, {i % cpus})
        # The fleet and PostgreSQL get the cores no server has (all of them when none is left).
        spare = set(range(replicas, cpus)) or set(range(cpus))
        for pid in postgres_pids(db.pgdata):
            pin_process(pid, spare)
        settings = {"width": 2048, "height": 2048, "tile_size": TILE, "noise_threshold": 0}
        settings["max_spp"] = 1 << 20
        with Client(farms[0].url) as client:
            for n in range(replicas):
                client.submit(ROOT / "examples" / "cornell-box.gltf", settings=settings,
                              name=f"load {n}")  # fmt: skip
            deadline = time.monotonic() + 60
            while sorted(r["jobs_owned"] for r in client.replicas() if r["live"]) != [1] * replicas:
                if time.monotonic() > deadline:
                    raise RuntimeError(f"the servers did not share the jobs: {client.replicas()}")
                time.sleep(0.2)
        sent, messages = Value("q", 0), Value("q", 0)
        gen = Process(
            target=fleet,
            args=(
                [f.grpc_address for f in farms],
                workers,
                seconds + 5,
                sent,
                messages,
                spare,
                packed,
                render_s,
                cores,
                interval_s,
            ),
        )
        gen.start()
        time.sleep(5)  # warm-up: streams connected, first leases out
        pg = postgres_pids(db.pgdata)
        servers = [f.server.pid for f in farms]
        before = [scrape(f.url) for f in farms]
        cpu0, pg_cpu0, writes0, t0 = (
            total_cpu(servers),
            total_cpu(pg),
            database_writes(url),
            (time.monotonic()),
        )
        time.sleep(seconds)
        after = [scrape(f.url) for f in farms]
        cpu1, pg_cpu1, writes1, t1 = (
            total_cpu(servers),
            total_cpu(pg),
            database_writes(url),
            (time.monotonic()),
        )
        gen.join(timeout=120)
        if gen.is_alive():
            gen.kill()
    finally:
        for farm in farms:
            farm.stop(timeout=180)
        db.stop()
    merged = [a.get(MERGED, 0.0) - b.get(MERGED, 0.0) for a, b in zip(after, before, strict=True)]
    results = sum(merged)
    return {
        "replicas": replicas,
        "workers": workers,
        "streams": workers * replicas,
        "packed": packed,
        "render_s": render_s,
        "cores": cores,
        "result_interval_ms": interval_s * 1e3,
        # Over the whole run (warm-up included): how full the fleet's messages were.
        "results_per_message": sent.value / max(1, messages.value),
        "seconds": t1 - t0,
        "results_per_s": results / (t1 - t0),
        "results_per_s_per_replica": [m / (t1 - t0) for m in merged],
        "server_cpu_ms_per_result": 1e3 * (cpu1 - cpu0) / max(results, 1),
        "server_cpu_utilisation": (cpu1 - cpu0) / (t1 - t0) / replicas,
        "pg_transactions_per_result": (writes1[0] - writes0[0]) / max(results, 1),
        "pg_rows_written_per_result": (writes1[1] - writes0[1]) / max(results, 1),
        "pg_cpu_ms_per_result": 1e3 * (pg_cpu1 - pg_cpu0) / max(results, 1),
    }


def main() -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workers", type=int, default=1000)
    parser.add_argument("--replicas", default="1,2", help="farm sizes to measure, e.g. 1,2")
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--tile-cache-mb", type=int, default=2048,
                        help="each server's RENDERFARM_TILE_CACHE_MB")  # fmt: skip
    parser.add_argument("--render-s", type=float, default=0.25,
                        help="mean render time of a synthetic task (0: at once)")  # fmt: skip
    parser.add_argument("--cores", type=int, default=64,
                        help="tasks in flight on each synthetic worker's stream")  # fmt: skip
    parser.add_argument("--result-interval-ms", type=float, default=50.0,
                        help="least time between a worker's result messages")  # fmt: skip
    parser.add_argument("--no-pack", action="store_true",
                        help="one result a message (as workers before packing)")  # fmt: skip
    args = parser.parse_args()
    runs = []
    for replicas in (int(x) for x in args.replicas.split(",")):
        with tempfile.TemporaryDirectory(prefix="rf-load-") as data:
            run = measure(replicas, args.workers, args.seconds, args.tile_cache_mb, Path(data),
                          not args.no_pack, args.render_s, args.cores,
                          args.result_interval_ms / 1e3)  # fmt: skip
        runs.append(run)
        for key, value in run.items():
            if isinstance(value, list):
                value = ", ".join(f"{v:,.1f}" for v in value)
            print(f"{key:28} {value:,.3f}" if isinstance(value, float) else f"{key:28} {value}")
        print(file=sys.stderr)
    figures = {"tile": TILE, "cpu_count": os.cpu_count(), "runs": runs}
    write_results("replica_load", figures)
    return figures


if __name__ == "__main__":
    main()
