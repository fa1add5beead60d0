"""Server merge throughput through the real gRPC server, with synthetic workers.

A server runs pinned to one CPU core (every thread of it: asyncio, gRPC's poller and event
engine, the checkpoint thread); a load generator and the embedded PostgreSQL are pinned to the
other core. The generator opens several WorkerService streams that answer every Assign at once
with a pre-built 64x64 TileResult shaped like the C++ worker's: float32 sums and hit counts, and
albedo/normal sums only when the task does not say skip_aovs (the first 16 samples of a pixel).
The figures come from the server's own Prometheus metrics: results/s merged, MB/s of result
payload, and merge latency p50/p99 (interpolated within the histogram buckets). Writes
bench/results/server_merge.json (key `results_per_s`).

    .venv/bin/python bench/server_merge.py [--seconds 10] [--streams 4]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import random
import re
import sys
import tempfile
import time
from pathlib import Path

import grpc
import httpx
import numpy as np
from support.results import write_results

from renderfarm.cli.localfarm import LocalFarm
from renderfarm.client import ApiError, Client
from renderfarm.v1 import workers_pb2

ROOT = Path(__file__).resolve().parents[1]
TILE = 64
TARGET = 2000
EXTRA_ENV = {k: v for k, v in os.environ.items() if k.startswith("RENDERFARM_")}


def payload(count: int, aovs: bool) -> bytes:
    """The per-pixel arrays of a TileResult, serialised once (protobuf fields concatenate)."""
    rng = np.random.default_rng(count)
    result = workers_pb2.TileResult(
        rgb_sum=(rng.random(TILE * TILE * 3) * count).astype("<f4").tobytes(),
        luminance_m2=(rng.random(TILE * TILE) * count).astype("<f4").tobytes(),
        # Every batch carries its camera rays' hit counts (the alpha), as the C++ worker sends.
        coverage_sum=rng.integers(0, count + 1, TILE * TILE).astype("<f4").tobytes(),
    )
    if aovs:
        result.albedo_sum = np.full(TILE * TILE * 3, 0.5 * count, "<f4").tobytes()
        result.normal_sum = np.full(TILE * TILE * 3, 0.5 * count, "<f4").tobytes()
    return result.SerializeToString()


def varint(n: int) -> bytes:
    out = bytearray()
    while True:
        byte, n = n & 0x7F, n >> 7
        out.append(byte | (0x80 if n else 0))
        if not n:
            return bytes(out)


RESULT_TAG = b"\x12"  # WorkerMessage.result: field 2, length-delimited
RESULTS_TAG = b"\x2a"  # WorkerMessage.results: field 5, length-delimited
PACKED_TAG = b"\x0a"  # TileResults.results: field 1, length-delimited
MAX_PACKED = 64  # results in one message at most (the C++ ResultPacker's kMaxResults)


async def synthetic_worker(
    address: str,
    name: str,
    in_flight: int,
    stop_at: float,
    packed: bool = True,
    render_s: float = 0.0,
    interval_s: float = 0.0,
) -> tuple[int, int, int]:
    """One worker stream rendering its tasks in no time (render_s 0: a result is ready when
    its Assign comes) or in a time drawn uniformly from 0.5 to 1.5 x render_s; returns
    (results, bytes, messages). Messages are framed by hand from a pre-serialised payload so
    that the load generator costs little CPU per result.

    Results leave as the C++ worker's ResultPacker sends them: a message goes when the stream
    takes it and interval_s (`--result-interval-ms`) has passed since the last one, or at once
    when 64 results fill it, with every result ready by then, at most 64 (one TileResults
    message, if the worker is packed and the server's Welcome says packed too), so a server
    that reads slowly gets fuller messages; unpacked, one message per result."""
    payloads: dict[tuple[int, bool], bytes] = {}
    sent = sent_bytes = messages = 0
    loop = asyncio.get_running_loop()
    rng = random.Random(name)
    ready: list[bytes] = []  # results waiting for the stream
    wake = asyncio.Event()
    pack = False

    def result(task) -> bytes:
        key = (task.sample_count, not task.skip_aovs)
        arrays = payloads.get(key)
        if arrays is None:
            arrays = payloads[key] = payload(*key)
        header = workers_pb2.TileResult(
            task_id=task.task_id,
            job_id=task.job_id,
            tile_index=task.tile_index,
            batch_index=task.batch_index,
            sample_start=task.sample_start,
            sample_count=task.sample_count,
            rect=task.rect,
            render_seconds=0.01,
        ).SerializeToString()
        return header + arrays

    def finish(task) -> None:
        ready.append(result(task))
        wake.set()

    hello = workers_pb2.Hello(worker_id=name, hostname="bench", cores=in_flight)
    hello.max_in_flight = in_flight
    hello.packed = packed

    async def requests():
        nonlocal sent, sent_bytes, messages
        yield workers_pb2.WorkerMessage(hello=hello).SerializeToString()
        last = -float("inf")
        while True:
            await wake.wait()
            wake.clear()
            if time.monotonic() > stop_at:
                return
            wait = last + interval_s - time.monotonic()
            if wait > 0 and len(ready) < MAX_PACKED:
                await asyncio.sleep(wait)  # more results may come meanwhile
            last = time.monotonic()
            inners = ready[:MAX_PACKED]
            del ready[:MAX_PACKED]
            if ready:
                wake.set()
            sent += len(inners)
            sent_bytes += sum(len(i) for i in inners)
            if pack and len(inners) > 1:
                body = b"".join(PACKED_TAG + varint(len(i)) + i for i in inners)
                messages += 1
                yield RESULTS_TAG + varint(len(body)) + body
            else:
                for inner in inners:
                    messages += 1
                    yield RESULT_TAG + varint(len(inner)) + inner

    async with grpc.aio.insecure_channel(
        address, options=[("grpc.max_send_message_length", 64 << 20)]
    ) as channel:
        connect = channel.stream_stream(
            "/renderfarm.v1.WorkerService/Connect",
            request_serializer=lambda raw: raw,
            response_deserializer=workers_pb2.ServerMessage.FromString,
        )
        call = connect(requests())
        async for msg in call:
            if time.monotonic() > stop_at:
                break
            kind = msg.WhichOneof("msg")
            if kind == "welcome":
                pack = packed and msg.welcome.packed
                continue
            tasks = [msg.assign.task] if kind == "assign" else []
            if kind == "assigns":
                tasks = [a.task for a in msg.assigns.assigns]
            for task in tasks:
                if render_s > 0:
                    loop.call_later(rng.uniform(0.5, 1.5) * render_s, finish, task)
                else:
                    finish(task)
        wake.set()
        call.cancel()
    return sent, sent_bytes, messages


def load_generator(
    address: str, streams: int, seconds: float, mean_bytes, packed: bool = True
) -> None:
    os.sched_setaffinity(0, {1 % os.cpu_count()})
    stop_at = time.monotonic() + seconds

    async def run():
        counts = await asyncio.gather(
            *(synthetic_worker(address, f"bench-{i}", 16, stop_at, packed) for i in range(streams))
        )
        sent, sent_bytes = sum(c[0] for c in counts), sum(c[1] for c in counts)
        messages = sum(c[2] for c in counts)
        print(f"load generator sent {sent} results in {messages} messages", file=sys.stderr)
        mean_bytes.value = sent_bytes / max(1, sent)

    asyncio.run(run())


def pin_process(pid: int, cpus: set[int]) -> None:
    """Pin every thread of a process (threads started later inherit it from their parent)."""
    for tid in os.listdir(f"/proc/{pid}/task"):
        with contextlib.suppress(ProcessLookupError):
            os.sched_setaffinity(int(tid), cpus)


def postgres_pids(data: Path) -> list[int]:
    """The embedded PostgreSQL's postmaster and its children (later ones inherit its pinning);
    none when the server uses a database of its own (RENDERFARM_DATABASE_URL)."""
    pidfile = data / "pg" / "postmaster.pid"
    if not pidfile.exists():
        return []
    postmaster = int(pidfile.read_text().split()[0])
    found = [postmaster]
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            with contextlib.suppress(OSError):
                # /proc/PID/stat: "pid (comm) state ppid ..."; comm may hold spaces.
                fields = (entry / "stat").read_text().rpartition(")")[2].split()
                if int(fields[1]) == postmaster:
                    found.append(int(entry.name))
    return found


def scrape(url: str) -> dict[str, float]:
    text = httpx.get(f"{url}/metrics", timeout=10).text
    values = {}
    for line in text.splitlines():
        if line.startswith("#") or not line.strip():
            continue
        name, _, value = line.rpartition(" ")
        values[name] = float(value)
    return values


def quantile(before: dict, after: dict, q: float) -> float:
    """Quantile of renderfarm_merge_latency_seconds observed between two scrapes."""
    buckets = []
    for name, value in after.items():
        m = re.fullmatch(r'renderfarm_merge_latency_seconds_bucket\{le="([^"]+)"\}', name)
        if m:
            buckets.append((float(m.group(1)), value - before.get(name, 0.0)))
    buckets.sort()
    total = buckets[-1][1]
    rank = q * total
    lower_bound, lower_count = 0.0, 0.0
    for bound, count in buckets:
        if count >= rank:
            if bound == float("inf"):
                return lower_bound
            share = (rank - lower_count) / max(count - lower_count, 1e-12)
            return lower_bound + share * (bound - lower_bound)
        lower_bound, lower_count = bound, count
    return lower_bound


def main() -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--streams", type=int, default=4)
    parser.add_argument("--no-pack", action="store_true",
                        help="one result a message (as workers before packing)")  # fmt: skip
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="rf-bench-") as data:
        farm = LocalFarm(workers=0, data_dir=Path(data), env=EXTRA_ENV)
        farm.start()
        try:
            pin_process(farm.server.pid, {0})
            for pid in postgres_pids(Path(data)):
                pin_process(pid, {1 % os.cpu_count()})
            with Client(farm.url) as client:
                settings = {
                    "width": 4096,
                    "height": 4096,
                    "tile_size": TILE,
                    "noise_threshold": 0,
                    "max_spp": 1 << 20,
                }
                job = client.submit(ROOT / "examples" / "cornell-box.gltf", settings=settings)
            from multiprocessing import Process, Value

            mean_bytes = Value("d", 0.0)
            gen = Process(
                target=load_generator,
                args=(
                    farm.grpc_address,
                    args.streams,
                    args.seconds + 3,
                    mean_bytes,
                    not args.no_pack,
                ),  # fmt: skip
            )
            gen.start()
            time.sleep(3)  # warm-up: streams connected, first leases out
            before, t0 = scrape(farm.url), time.monotonic()
            time.sleep(args.seconds)
            after, t1 = scrape(farm.url), time.monotonic()
            gen.join(timeout=60)
            with Client(farm.url) as client:
                # Clean-up: the server, one core flooded with results, may still be storing
                # the job (503 with Retry-After): ask again for up to a minute, then stop anyway.
                deadline = time.monotonic() + 60
                while True:
                    try:
                        client.cancel(job["id"])
                        break
                    except ApiError as e:
                        if e.status != 503 or time.monotonic() > deadline:
                            raise
                        time.sleep(1)
        except Exception:
            print((Path(data) / "server.log").read_text()[-3000:], file=sys.stderr)
            raise
        finally:
            # The last checkpoint of a 4096-tile job is about a gigabyte: give it time.
            farm.stop(timeout=180)
    merged_key = 'renderfarm_tasks_completed_total{outcome="merged"}'
    results = after.get(merged_key, 0.0) - before.get(merged_key, 0.0)
    elapsed = t1 - t0
    bytes_per_result = mean_bytes.value  # mean TileResult size the load generator sent
    figures = {
        "results_per_s": results / elapsed,
        "mb_per_s": results * bytes_per_result / elapsed / 1e6,
        "merge_latency_p50_ms": quantile(before, after, 0.5) * 1e3,
        "merge_latency_p99_ms": quantile(before, after, 0.99) * 1e3,
        "target_results_per_s": TARGET,
        "tile": TILE,
        "streams": args.streams,
        "packed": not args.no_pack,
        "seconds": elapsed,
        "server_cores": 1,
    }
    for key, value in figures.items():
        print(f"{key:24} {value:,.3f}" if isinstance(value, float) else f"{key:24} {value}")
    write_results("server_merge", figures)
    return figures


if __name__ == "__main__":
    main()
