"""A real Prometheus (Debian's /usr/bin/prometheus) scrapes the farm's /metrics every second
during a render, and PromQL over what it stored shows the samples rate; `promtool check metrics`
accepts the exposition. Everything on loopback; every wait bounded."""

from __future__ import annotations

import shutil
import subprocess

import httpx
import pytest

from renderfarm.cli.localfarm import free_port
from renderfarm.client import Client

from .conftest import CORNELL
from .scrape import metric
from .tools import require_tool
from .waiting import wait_until

PROMETHEUS = shutil.which("prometheus") or "/usr/bin/prometheus"
PROMTOOL = shutil.which("promtool") or "/usr/bin/promtool"


@pytest.fixture(scope="module", autouse=True)
def _prometheus_installed():
    require_tool(
        bool(shutil.which(PROMETHEUS) and shutil.which(PROMTOOL)),
        "Debian's prometheus package is not installed (scripts/install-deps.sh installs it)",
    )


def _wait_for_workers(farm, count: int = 2) -> None:
    with Client(farm.url) as client:
        wait_until(lambda: len(client.workers()) >= count, 30, f"{count} workers connected")


def test_promtool_accepts_the_exposition(farm, tmp_path):
    _wait_for_workers(farm)
    text = httpx.get(f"{farm.url}/metrics", timeout=10).text
    for name in (
        "renderfarm_jobs",
        "renderfarm_queue_depth",
        "renderfarm_tasks_leased",
        "renderfarm_leases_expired_total",
        "renderfarm_tasks_assigned_total",
        "renderfarm_tasks_completed_total",
        "renderfarm_tasks_failed_total",
        "renderfarm_task_duration_seconds_bucket",
        "renderfarm_merge_latency_seconds_bucket",
        "renderfarm_samples_merged_total",
        "renderfarm_worker_samples_per_second",
        "renderfarm_worker_rays_per_second",
        "renderfarm_workers_connected",
        "renderfarm_database_errors_total",
    ):
        assert f"\n{name}" in text, f"{name} missing from /metrics"
    checked = subprocess.run(
        [PROMTOOL, "check", "metrics"], input=text, capture_output=True, text=True, timeout=60
    )
    assert checked.returncode == 0, checked.stdout + checked.stderr


def test_the_samples_counter_counts_only_the_pixels_a_per_pixel_job_rendered(farm):
    _wait_for_workers(farm)
    with Client(farm.url, timeout=60) as client:
        busy = ("queued", "running")
        wait_until(lambda: not [j for j in client.list()["jobs"] if j["state"] in busy], 120,
                   "the shared farm to finish earlier tests' jobs")  # fmt: skip
        before = metric(farm.url, "renderfarm_samples_merged_total")
        settings = {"width": 32, "height": 32, "tile_size": 16, "max_spp": 256,
                    "noise_threshold": 0.1, "adaptive": "pixel", "seed": 5}  # fmt: skip
        job = client.submit(CORNELL, settings=settings, name="counted")
        done = client.wait(job["id"], poll_s=0.2, timeout_s=300)
    assert done["state"] == "completed"
    merged = done["progress"]["samples_merged"]
    assert merged < 256 * 32 * 32, "no pixel stopped early: the test shows nothing"
    assert metric(farm.url, "renderfarm_samples_merged_total") - before == merged


def test_prometheus_scrapes_a_render_and_promql_sees_the_samples_rate(farm, tmp_path):
    _wait_for_workers(farm)
    port = free_port()
    target = farm.url.removeprefix("http://")
    config = tmp_path / "prometheus.yml"
    config.write_text(
        "global:\n  scrape_interval: 1s\n  evaluation_interval: 1s\n"
        "scrape_configs:\n  - job_name: renderfarm\n    scrape_interval: 1s\n"
        f"    static_configs:\n      - targets: ['{target}']\n"
    )
    log = open(tmp_path / "prometheus.log", "wb")  # noqa: SIM115
    prometheus = subprocess.Popen(
        [PROMETHEUS, f"--config.file={config}", f"--storage.tsdb.path={tmp_path / 'tsdb'}",
         f"--web.listen-address=127.0.0.1:{port}"],
        stdout=log, stderr=subprocess.STDOUT,
    )  # fmt: skip
    api = f"http://127.0.0.1:{port}/api/v1"
    try:

        def farm_scraped() -> bool:
            assert prometheus.poll() is None, (tmp_path / "prometheus.log").read_text()
            try:
                targets = httpx.get(f"{api}/targets", timeout=5).json()["data"]["activeTargets"]
            except (httpx.HTTPError, ValueError, KeyError):
                return False
            return bool(targets) and targets[0]["health"] == "up"

        wait_until(farm_scraped, 60, "Prometheus to report the farm as a healthy target", 0.5)
        with Client(farm.url, timeout=60) as client:
            settings = {"width": 96, "height": 96, "tile_size": 16, "max_spp": 64,
                        "noise_threshold": 0, "seed": 11}  # fmt: skip
            job = client.submit(CORNELL, settings=settings, name="scraped")
            query = "sum(rate(renderfarm_samples_merged_total[15s]))"

            def samples_rate() -> float:
                result = httpx.get(f"{api}/query", params={"query": query}, timeout=5).json()
                values = result["data"]["result"]
                rate = float(values[0]["value"][1]) if values else 0.0
                return rate if rate > 0 else 0.0

            rate = wait_until(samples_rate, 120, "PromQL to see samples being merged", 0.5)
            done = client.wait(job["id"], poll_s=0.5, timeout_s=300)
        assert done["state"] == "completed"
        assert rate > 0
        # The workers' own figures, sent in heartbeats, reach Prometheus per worker.
        result = httpx.get(
            f"{api}/query", params={"query": "renderfarm_worker_samples_per_second"}, timeout=5
        ).json()
        assert {r["metric"]["worker"] for r in result["data"]["result"]}, result
    finally:
        prometheus.terminate()
        try:
            prometheus.wait(timeout=30)
        except subprocess.TimeoutExpired:
            prometheus.kill()
            prometheus.wait()
        log.close()
