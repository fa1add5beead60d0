"""An 8192x8192 job on a local farm: the server's peak memory, preview latency and image times.

A local farm (embedded PostgreSQL, server, 2 workers with 1 thread each on this 2-core machine,
default server settings) renders the Cornell box at 8192x8192 with max_spp 4 (every tile stops
at 4 samples per pixel) to completion. Meanwhile the server process's resident memory is
sampled (VmRSS of /proc/PID/status, every 50 ms), and at a quarter, half and three quarters of
the tiles merged the dashboard's preview (`image.png?max_size=2048`) is fetched: its latency is
from the request to the last byte. After the job: the EXR (all layers, full resolution, streamed
to a file; zip-compressed, and with `compression=none`), the full-resolution PNG and the preview
again, each timed the same way and with the server's CPU seconds for it, and the peak (VmHWM)
read just before the server stops. Last, a second such job is started and the
server gets SIGTERM once the first tiles have merged: the figure is the time it takes to exit
(with the default drain timeout, 30 s). Writes bench/results/large_image.json. Goals: peak RSS
under 1.5 GB, preview under 5 s, EXR under 20 s.

    .venv/bin/python bench/large_image.py     # BENCH_SIZE=8192, BENCH_SPP=4
"""

from __future__ import annotations

import os
import signal
import statistics
import tempfile
import threading
import time
from pathlib import Path

from support.results import write_results

from renderfarm.cli.localfarm import LocalFarm
from renderfarm.client import Client

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "examples" / "cornell-box.gltf"
SIZE = int(os.environ.get("BENCH_SIZE", "8192"))
SPP = int(os.environ.get("BENCH_SPP", "4"))
PREVIEW = 2048  # the dashboard's max_size


def status_kb(pid: int, field: str) -> int:
    """A figure of /proc/PID/status in kB (VmRSS, VmHWM)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise KeyError(field)


class RssSampler(threading.Thread):
    """Polls a process's VmRSS until stopped; keeps the largest value."""

    def __init__(self, pid: int):
        super().__init__(daemon=True)
        self.pid, self.peak_kb, self.done = pid, 0, threading.Event()

    def run(self) -> None:
        while not self.done.wait(0.05):
            try:
                self.peak_kb = max(self.peak_kb, status_kb(self.pid, "VmRSS"))
            except (OSError, KeyError):
                return


def cpu_seconds(pid: int) -> float:
    """User and system CPU time of a process so far (/proc/PID/stat)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def fetch_seconds(client: Client, job_id: str, fmt: str, out: Path, **params) -> float:
    """Seconds from the request until the last byte of the image is written to `out`."""
    started = time.perf_counter()
    with client.http.stream(
        "GET", f"/api/v1/jobs/{job_id}/image.{fmt}", params=params, timeout=600
    ) as response:
        response.raise_for_status()
        with out.open("wb") as f:
            for chunk in response.iter_bytes(1 << 20):
                f.write(chunk)
    return time.perf_counter() - started


def wait_until(predicate, timeout_s: float, what: str, poll_s: float = 0.5):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(poll_s)
    raise TimeoutError(f"timed out after {timeout_s} s waiting for {what}")


def main() -> dict:
    settings = {"width": SIZE, "height": SIZE, "max_spp": SPP}
    figures: dict = {"resolution": SIZE, "max_spp": SPP, "workers": 2, "threads_per_worker": 1}
    with tempfile.TemporaryDirectory(prefix="rf-bench-") as tmp:
        data, scratch = Path(tmp) / "farm", Path(tmp)
        with LocalFarm(workers=2, data_dir=data, threads=1) as farm, Client(farm.url) as c:
            pid = farm.server.pid
            wait_until(lambda: len(c.workers()) == 2, 60, "two workers", 0.05)
            figures["server_rss_idle_mb"] = status_kb(pid, "VmRSS") / 1024
            sampler = RssSampler(pid)
            sampler.start()
            started = time.perf_counter()
            job = c.submit(SCENE, settings=settings, name="large")
            previews, preview_cpu = [], []
            for fraction in (0.25, 0.5, 0.75):

                def reached(f=fraction):
                    p = c.get(job["id"])["progress"]
                    return p["tiles_done"] >= f * p["tiles_total"] or p["eta_s"] == 0

                wait_until(reached, 3600, f"{fraction:.0%} of the tiles")
                png = scratch / "preview.png"
                cpu = cpu_seconds(pid)
                previews.append(fetch_seconds(c, job["id"], "png", png, max_size=PREVIEW))
                preview_cpu.append(cpu_seconds(pid) - cpu)
            job = c.wait(job["id"], poll_s=0.5, timeout_s=3600)
            assert job["state"] == "completed", job
            figures["render_s"] = time.perf_counter() - started
            figures["samples_per_s"] = job["progress"]["samples_merged"] / figures["render_s"]
            # Each image after the job, timed (wall, and the server's CPU seconds for it: on a
            # machine shared with other work the wall time says more about the neighbours).
            for key, fmt, params in (
                ("exr", "exr", {}),
                ("exr_uncompressed", "exr", {"compression": "none"}),
                ("png_full_resolution", "png", {}),
                ("preview_after", "png", {"max_size": PREVIEW}),
            ):
                out = scratch / f"{key}.{fmt}"
                cpu = cpu_seconds(pid)
                figures[f"{key}_s"] = fetch_seconds(c, job["id"], fmt, out, **params)
                figures[f"{key}_server_cpu_s"] = cpu_seconds(pid) - cpu
                figures[f"{key}_mb"] = out.stat().st_size / 1e6
                out.unlink()
            figures["preview_during_s"] = previews
            figures["preview_during_s_max"] = max(previews)
            figures["preview_during_s_median"] = statistics.median(previews)
            figures["preview_during_server_cpu_s"] = preview_cpu
            sampler.done.set()
            sampler.join()
            figures["server_rss_peak_mb"] = status_kb(pid, "VmHWM") / 1024
            figures["server_rss_peak_sampled_mb"] = sampler.peak_kb / 1024
            figures["server_rss_after_mb"] = status_kb(pid, "VmRSS") / 1024

            # SIGTERM with a large job running: the time until the server has exited.
            second = c.submit(SCENE, settings=settings, name="large, stopped")

            def merged():
                return c.get(second["id"])["progress"]["tiles_previewed"] >= 64

            wait_until(merged, 600, "the second job's first tiles")
            stop_started = time.perf_counter()
            farm.server.send_signal(signal.SIGTERM)
            code = farm.server.wait(timeout=300)
            figures["sigterm_exit_s"] = time.perf_counter() - stop_started
            figures["sigterm_exit_code"] = code
            figures["drain_timeout_s"] = 30.0
    figures["goals"] = {"server_rss_peak_mb": 1536, "preview_s": 5.0, "exr_s": 20.0}
    figures["load_average_1m_at_end"] = os.getloadavg()[0]
    for key, value in figures.items():
        print(f"{key:28} {value}")
    write_results("large_image", figures)
    return figures


if __name__ == "__main__":
    main()
