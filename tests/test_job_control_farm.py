"""Job control on a real farm (embedded PostgreSQL, server, real workers): continue equals a
job submitted with the final settings bit for bit; pause, resume and dependencies survive a
server restart; a failed job is retried with what it had merged; the CLI commands."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import httpx
import numpy as np
import pytest

from renderfarm.cli.localfarm import LocalFarm, stop_processes
from renderfarm.client import ApiError, Client
from renderfarm.infra.images import read_exr

from .conftest import CORNELL
from .waiting import wait_until

FAST = {"RENDERFARM_CHECKPOINT_INTERVAL_S": "0.5"}
SMALL = {"width": 48, "height": 48, "tile_size": 16, "seed": 5, "min_spp": 4}
CLI = [sys.executable, "-m", "renderfarm"]


@pytest.fixture(scope="module")
def farm(tmp_path_factory):
    with LocalFarm(workers=2, data_dir=tmp_path_factory.mktemp("jobctl"), threads=1, env=FAST) as f:
        with Client(f.url) as c:
            wait_until(lambda: len(c.workers()) == 2, 30, "two workers")
        yield f


@pytest.fixture()
def client(farm):
    with Client(farm.url, timeout=60) as c:
        yield c


def exr_channels(client: Client, job_id: str, tmp_path: Path) -> dict[str, np.ndarray]:
    path = tmp_path / f"{job_id}.exr"
    path.write_bytes(client.image(job_id, "exr"))
    return read_exr(str(path))


def assert_identical(client: Client, a: str, b: str, tmp_path: Path) -> None:
    """Every layer of the two jobs' EXRs bit for bit, and the same tile stops (batch, spp and
    float64 error of each tile)."""
    ja, jb = client.get(a), client.get(b)
    assert ja["progress"]["samples_merged"] == jb["progress"]["samples_merged"]
    assert sorted(ja["stops"], key=lambda s: s["tile"]) == sorted(
        jb["stops"], key=lambda s: s["tile"]
    )
    ca, cb = exr_channels(client, a, tmp_path), exr_channels(client, b, tmp_path)
    assert sorted(ca) == sorted(cb)
    for name in ca:
        differ = np.argwhere(ca[name] != cb[name])
        assert not differ.size, f"channel {name} differs at {len(differ)} pixels: {differ[:4]}"


CONTINUES = [
    # No noise threshold: 64 spp is a batch boundary, so every tile carries on.
    ({"noise_threshold": 0, "max_spp": 64}, {"max_spp": 160}, 0),
    # 40 is not one (the batch of 32..64 was cut at 40): every tile renders again.
    ({"noise_threshold": 0, "max_spp": 40}, {"max_spp": 96}, 9),
    # With a noise threshold: lower it and raise max_spp.
    ({"noise_threshold": 0.08, "max_spp": 128}, {"noise_threshold": 0.03, "max_spp": 256}, None),
]


@pytest.mark.parametrize("first,more,again", CONTINUES)
def test_continue_equals_a_job_submitted_with_the_final_settings(
    client, tmp_path, first, more, again
):
    job = client.submit(CORNELL, settings={**SMALL, **first}, name="first pass")
    job = client.wait(job["id"], poll_s=0.1, timeout_s=300)
    assert job["state"] == "completed"
    before = job["progress"]["samples_merged"]
    continued = client.continue_job(job["id"], **more)
    assert continued["state"] in ("queued", "running", "completed")
    for key, value in more.items():
        assert continued["settings"][key] == value
    continued = client.wait(job["id"], poll_s=0.1, timeout_s=300)
    assert continued["state"] == "completed"
    assert continued["progress"]["samples_merged"] > before
    fresh = client.submit(CORNELL, settings={**SMALL, **first, **more}, name="from the start")
    fresh = client.wait(fresh["id"], poll_s=0.1, timeout_s=300)
    assert fresh["state"] == "completed"
    assert_identical(client, job["id"], fresh["id"], tmp_path)
    event = next(e for e in client.events(job["id"]) if e["kind"] == "job_continued")
    assert event["data"]["from"] == "completed" and event["data"]["to"] == "queued"
    if again is not None:
        assert event["data"].get("tiles_rendered_again", 0) == again


def test_continue_refuses_what_would_change_merged_batches(client):
    job = client.submit(CORNELL, settings={**SMALL, "max_spp": 8}, name="refusals")
    done = client.wait(job["id"], poll_s=0.1, timeout_s=300)
    assert done["state"] == "completed"
    for body, field in [
        ({"settings": {"seed": 6}}, "settings.seed"),
        ({"settings": {"width": 64}}, "settings.width"),
        ({"settings": {"max_spp": 4}}, "settings.max_spp"),
        ({"settings": {"noise_threshold": 0.5}}, "settings.noise_threshold"),
        ({"settings": {}}, "settings"),
        ({"bogus": 1}, "bogus"),
    ]:
        r = httpx.post(f"{client.url}/api/v1/jobs/{job['id']}/continue", json=body, timeout=30)
        assert (r.status_code, r.json()["field"]) == (400, field), (body, r.text)
    assert client.get(job["id"])["state"] == "completed"


def test_update_priority_and_name_with_validation(client):
    job = client.submit(CORNELL, settings={**SMALL, "max_spp": 4}, name="before")
    updated = client.update(job["id"], priority=12, name="after")
    assert (updated["settings"]["priority"], updated["name"]) == (12, "after")
    for body, field in [
        ({"priority": 5000}, "priority"),
        ({"priority": "high"}, "priority"),
        ({"priority": 1.5}, "priority"),
        ({"name": 7}, "name"),
        ({"colour": "red"}, "colour"),
    ]:
        r = httpx.patch(f"{client.url}/api/v1/jobs/{job['id']}", json=body, timeout=30)
        assert (r.status_code, r.json()["field"]) == (400, field), (body, r.text)
    done = client.wait(job["id"], poll_s=0.1, timeout_s=300)
    assert (done["settings"]["priority"], done["name"]) == (12, "after")
    kinds = [e["kind"] for e in client.events(job["id"])]
    assert "job_updated" in kinds


def test_a_dependency_that_is_cancelled_fails_the_jobs_after_it(client):
    # Paused before any worker takes it, so it cannot complete before it is cancelled.
    first = client.submit(CORNELL, settings={**SMALL, "max_spp": 64}, name="first")
    client.pause(first["id"])
    second = client.submit(CORNELL, settings={**SMALL, "max_spp": 4}, after=[first["id"]])
    assert second["state"] == "waiting" and second["after"] == [first["id"]]
    with pytest.raises(ApiError) as refused:
        client.submit(CORNELL, settings=SMALL, after=["0" * 12])
    assert (refused.value.status, refused.value.field) == (400, "after")
    client.cancel(first["id"])
    failed = client.wait(second["id"], poll_s=0.1, timeout_s=60)
    assert failed["state"] == "failed"
    assert failed["error"] == f"dependency {first['id']} was cancelled"
    with pytest.raises(ApiError) as refused:
        client.submit(CORNELL, settings=SMALL, after=[first["id"]])
    assert (refused.value.status, refused.value.field) == (400, "after")
    # A retry waits again, and fails again for the same reason.
    assert client.retry(second["id"])["state"] == "waiting"
    again = client.wait(second["id"], poll_s=0.1, timeout_s=60)
    assert again["state"] == "failed" and first["id"] in again["error"]


def test_the_cli_controls_jobs(farm, client):
    env = {**os.environ, "RENDERFARM_URL": farm.url}
    env.pop("RENDERFARM_TOKEN", None)

    def run(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run(CLI + list(args), capture_output=True, text=True, timeout=120,
                              env=env)  # fmt: skip

    tiny = ["--width", "32", "--height", "32", "--tile-size", "16", "--spp", "4"]
    # 4M samples: seconds of work for two one-thread workers, so it is paused unfinished.
    slow = ["--width", "32", "--height", "32", "--tile-size", "16", "--spp", "4096",
            "--noise-threshold", "0"]  # fmt: skip
    first = json.loads(run("submit", str(CORNELL), "--json", *slow).stdout)
    paused = run("pause", first["id"])
    assert paused.returncode == 0 and paused.stdout.split() == [first["id"], "paused"]
    after = run("submit", str(CORNELL), "--json", "--after", first["id"], *tiny)
    assert json.loads(after.stdout)["state"] == "waiting", after.stderr
    renamed = json.loads(
        run("update", first["id"], "--priority", "9", "--name", "cli", "--json").stdout
    )
    assert (renamed["settings"]["priority"], renamed["name"]) == (9, "cli")
    assert run("resume", first["id"]).stdout.split()[1] in ("queued", "running", "completed")
    assert run("watch", first["id"], "--json").returncode == 0
    more = run("continue", first["id"], "--max-spp", "4160")
    assert more.returncode == 0, more.stderr
    done = client.wait(first["id"], poll_s=0.1, timeout_s=120)
    assert done["progress"]["mean_spp"] == 4160
    client.wait(json.loads(after.stdout)["id"], poll_s=0.1, timeout_s=120)
    refused = run("continue", first["id"], "--max-spp", "2")
    assert refused.returncode == 1 and "settings.max_spp" in refused.stderr
    usage = run("update", first["id"])
    assert usage.returncode == 2 and "--priority or --name" in usage.stderr
    retried = run("retry", first["id"])
    assert retried.returncode == 1 and "completed; it cannot be retried" in retried.stderr


def test_paused_waiting_and_continued_jobs_survive_a_server_restart(tmp_path):
    """The server stops (gracefully) and starts again: a paused job is paused with what it
    had merged, a waiting job still waits, and a job continued just before the stop resumes
    with its replayed plans and still equals a job submitted with its final settings."""
    first = {**SMALL, "width": 96, "height": 96, "noise_threshold": 0.08, "max_spp": 64}
    more = {"noise_threshold": 0.02, "max_spp": 512}
    big = {"width": 96, "height": 96, "tile_size": 16, "max_spp": 256, "noise_threshold": 0}
    with LocalFarm(workers=2, data_dir=tmp_path / "farm", threads=1, env=FAST) as farm:
        with Client(farm.url) as client:
            wait_until(lambda: len(client.workers()) == 2, 30, "two workers")
            job = client.submit(CORNELL, settings=big, name="paused")
            wait_until(
                lambda: client.get(job["id"])["progress"]["samples_merged"] > 0, 120, "a merge"
            )
            paused = client.pause(job["id"])
            assert paused["state"] == "paused"
            # The workers hand its tasks back; then the farm renders another job, not it.
            wait_until(
                lambda: all(w["tasks_in_flight"] == 0 for w in client.workers()),
                30,
                "the paused job's tasks returned",
            )
            held = client.get(job["id"])["progress"]["samples_merged"]
            waiter = client.submit(CORNELL, settings=SMALL | {"max_spp": 4}, after=[job["id"]])
            other = client.submit(CORNELL, settings=SMALL | {"max_spp": 4}, name="meanwhile")
            assert client.wait(other["id"], poll_s=0.1, timeout_s=120)["state"] == "completed"
            assert client.get(job["id"])["progress"]["samples_merged"] == held
            assert client.get(job["id"])["state"] == "paused"
            assert client.get(waiter["id"])["state"] == "waiting"
            cont = client.submit(CORNELL, settings=first, name="continued")
            assert client.wait(cont["id"], poll_s=0.1, timeout_s=120)["state"] == "completed"
            assert client.continue_job(cont["id"], **more)["state"] in ("queued", "running")
            # Every merged batch is in the checkpoint before the restart.
            wait_until(
                lambda: (
                    client.list(state="paused")["jobs"]
                    and client.list(state="paused")["jobs"][0]["progress"]["samples_merged"] == held
                ),
                30,
                "the paused job stored",
            )
        stop_processes([farm.server], timeout=30)
        farm.start_server()
        with Client(farm.url) as client:
            resumed = client.get(job["id"])
            assert resumed["state"] == "paused"
            assert resumed["progress"]["samples_merged"] == held
            assert client.get(waiter["id"])["state"] == "waiting"
            wait_until(lambda: len(client.workers()) == 2, 30, "the workers back")
            assert client.get(job["id"])["progress"]["samples_merged"] == held
            client.resume(job["id"])
            done = client.wait(job["id"], poll_s=0.2, timeout_s=600)
            assert done["state"] == "completed"
            assert done["progress"]["samples_merged"] == 96 * 96 * 256
            released = client.wait(waiter["id"], poll_s=0.1, timeout_s=120)
            assert released["state"] == "completed"
            continued = client.wait(cont["id"], poll_s=0.1, timeout_s=300)
            assert continued["state"] == "completed"
            fresh = client.submit(CORNELL, settings={**first, **more}, name="from the start")
            assert client.wait(fresh["id"], poll_s=0.1, timeout_s=300)["state"] == "completed"
            assert_identical(client, cont["id"], fresh["id"], tmp_path)
            kinds = [e["kind"] for e in client.events(job["id"])]
            assert kinds.index("job_paused") < kinds.index("job_resumed")
            assert "job_released" in [e["kind"] for e in client.events(waiter["id"])]


def test_a_failed_job_is_retried_with_what_it_had_merged(tmp_path):
    """A worker with a 1 s task budget renders the small first batches of one 256x256 tile and
    fails on a large one (the job fails); a retry on an unlimited worker carries on from the
    merged batches and ends with the image of a job that never failed. The tile is sized so
    that the first batch (1 spp, 65k samples) takes a fraction of the budget even on a busy
    machine and a 64-spp batch (4.2M samples) several times it on a fast one."""
    settings = {"width": 256, "height": 256, "tile_size": 256, "max_spp": 128,
                "noise_threshold": 0, "seed": 2}  # fmt: skip
    with LocalFarm(workers=0, data_dir=tmp_path / "farm") as farm:
        farm.add_workers(1, threads=1, extra_args=["--task-timeout-s", "1"])
        with Client(farm.url) as client:
            job = client.submit(CORNELL, settings=settings, name="fails")
            failed = client.wait(job["id"], poll_s=0.1, timeout_s=180)
            assert failed["state"] == "failed", failed
            merged = failed["progress"]["samples_merged"]
            assert 0 < merged < 256 * 256 * 128, failed
            stop_processes(farm.worker_procs)
            wait_until(lambda: not client.workers(), 30, "the limited worker gone")
            farm.add_workers(1, threads=2)
            retried = client.retry(job["id"])
            assert retried["state"] == "queued" and retried["error"] == ""
            assert retried["progress"]["samples_merged"] == merged
            done = client.wait(job["id"], poll_s=0.1, timeout_s=300)
            assert done["state"] == "completed"
            assert done["progress"]["samples_merged"] == 256 * 256 * 128
            fresh = client.submit(CORNELL, settings=settings, name="never failed")
            assert client.wait(fresh["id"], poll_s=0.1, timeout_s=300)["state"] == "completed"
            assert_identical(client, job["id"], fresh["id"], tmp_path)
            kinds = [e["kind"] for e in client.events(job["id"])]
            assert kinds.index("job_finished") < kinds.index("job_retried")
