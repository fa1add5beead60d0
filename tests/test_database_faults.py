"""Database faults on real processes (embedded PostgreSQL, server, C++ workers): the postmaster
killed mid-job, a job that finishes while the database is down and a server stopped then, the
answers of both APIs during an outage, and a burst of concurrent submissions.

Images are compared with an undisturbed render of the same job on the same farm, bit for bit:
the merge is deterministic, so the same scene, settings and seed give the same EXR channels and
the same PNG bytes whatever happened on the way.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import time
from pathlib import Path

import grpc
import httpx
import numpy as np
import psutil
import psycopg

from renderfarm.cli.localfarm import LocalFarm, stop_processes
from renderfarm.client import Client
from renderfarm.domain.scenes.pack import pack_gltf
from renderfarm.infra.embedded_db import pg_ctl
from renderfarm.infra.images import read_exr
from renderfarm.v1 import jobs_pb2, jobs_pb2_grpc, scenes_pb2, scenes_pb2_grpc

from .conftest import CORNELL
from .test_faults import FAST_LEASES, SETTINGS, TOTAL, metric
from .waiting import wait_until

TILES = (96 // 16) ** 2


def images_of(client: Client, job_id: str, tmp_path: Path) -> tuple[dict, bytes]:
    """Every EXR channel of the job's image, and its PNG preview's bytes."""
    path = tmp_path / f"{job_id}.exr"
    path.write_bytes(client.image(job_id, "exr"))
    return read_exr(str(path)), client.image(job_id, "png")


def assert_identical(got: tuple[dict, bytes], expected: tuple[dict, bytes]) -> None:
    channels, png = got
    assert sorted(channels) == sorted(expected[0])
    for name, values in expected[0].items():
        assert np.array_equal(channels[name], values), f"channel {name} differs"
    assert png == expected[1], "the PNG previews differ"


def postmaster_pid(pgdata: Path) -> int | None:
    """The pid postmaster.pid names, when that process is a live postgres (not a zombie)."""
    try:
        pid = int((pgdata / "postmaster.pid").read_text().split()[0])
        process = psutil.Process(pid)
        if process.status() == psutil.STATUS_ZOMBIE or "postgres" not in process.name():
            return None
        return pid
    except (OSError, ValueError, IndexError, psutil.Error):
        return None


def db_url(data: Path) -> str:
    return f"postgresql://postgres:@/postgres?host={data / 'pg'}"


def finished_events(data: Path) -> dict[str, int]:
    """job id -> number of job_finished events stored for it."""
    with psycopg.connect(db_url(data)) as conn:
        rows = conn.execute(
            "SELECT job_id, count(*) FROM events WHERE kind = 'job_finished' GROUP BY job_id"
        ).fetchall()
    return dict(rows)


def undisturbed(client: Client, tmp_path: Path) -> tuple[dict, bytes]:
    """Render the SETTINGS job once without faults: the image every other run must equal."""
    wait_until(lambda: len(client.workers()) == 2, 30, "two workers")
    ref = client.wait(client.submit(CORNELL, settings=SETTINGS)["id"], poll_s=0.2, timeout_s=600)
    assert ref["state"] == "completed"
    assert ref["progress"]["samples_merged"] == TOTAL
    return images_of(client, ref["id"], tmp_path)


def test_a_killed_postmaster_is_restarted_and_the_job_ends_with_the_same_image(tmp_path):
    """kill -9 of the embedded PostgreSQL's postmaster mid-job: the server starts it again (and
    logs it), is ready again as soon as it answers, and the job completes with the image of an
    undisturbed run, stored once."""
    data = tmp_path / "farm"
    pgdata = data / "pg"
    with LocalFarm(workers=2, data_dir=data, threads=1, env=FAST_LEASES) as farm:
        with Client(farm.url) as client:
            expected = undisturbed(client, tmp_path)
            job = client.submit(CORNELL, settings=SETTINGS)
            wait_until(
                lambda: client.get(job["id"])["progress"]["samples_merged"] > 0.2 * TOTAL,
                300,
                "20% merged",
            )
            killed = postmaster_pid(pgdata)
            assert killed is not None
            os.kill(killed, signal.SIGKILL)
            killed_at = time.monotonic()
            assert client.get(job["id"])["progress"]["samples_merged"] < TOTAL, (
                "the job ended before the postmaster was killed"
            )
            wait_until(lambda: postmaster_pid(pgdata) not in (None, killed), 60, "a new postmaster")
            restarted_s = time.monotonic() - killed_at
            wait_until(client.ready, 30, "the server to be ready again")
            ready_s = time.monotonic() - killed_at
            print(f"postmaster restarted after {restarted_s:.1f} s, ready after {ready_s:.1f} s")
            job = client.wait(job["id"], poll_s=0.2, timeout_s=600)
            assert job["state"] == "completed"
            assert job["progress"]["samples_merged"] == TOTAL
            assert_identical(images_of(client, job["id"], tmp_path), expected)
            # Also once the final state is read back from the database.
            stored = client.list(state="completed", page_size=10)["jobs"]
            assert job["id"] in [j["id"] for j in stored]
            assert finished_events(data)[job["id"]] == 1
    log = (data / "server.log").read_text()
    assert f"embedded PostgreSQL (pid {killed}) died" in log
    assert "restarted the embedded PostgreSQL" in log
    assert not (pgdata / "postmaster.pid").exists()


def test_a_job_finished_while_the_database_is_down_survives_a_shutdown(tmp_path):
    """The database stops mid-job; the job finishes in memory but is not reported completed
    while that cannot be stored; the server is stopped (SIGTERM) before the database is back and
    keeps what it merged in its spool; after a restart (which brings the embedded database back)
    the job is completed with the image of an undisturbed run and nothing is rendered again,
    and a job still running then resumes with every sample it had merged."""
    data = tmp_path / "farm"
    pgdata = data / "pg"
    with LocalFarm(workers=2, data_dir=data, threads=1, env=FAST_LEASES) as farm:
        with Client(farm.url) as client:
            expected = undisturbed(client, tmp_path)
            job = client.submit(CORNELL, settings=SETTINGS)
            # Rendered only once the first job has nothing left to lease (lower priority).
            long = client.submit(CORNELL, settings={**SETTINGS, "max_spp": 1 << 16, "priority": -1})
            wait_until(
                lambda: client.get(job["id"])["progress"]["samples_merged"] > 0.05 * TOTAL,
                300,
                "5% merged",
            )
            # A clean stop: the server leaves a database stopped on purpose alone.
            pg_ctl(pgdata, "stop", "-m", "fast", "-w")
            assert client.get(job["id"])["progress"]["samples_merged"] < TOTAL, (
                "the job ended before the database went away"
            )

            def merged_in_memory() -> bool:
                view = client.get(job["id"])
                assert view["state"] != "completed", "reported completed but not stored"
                p = view["progress"]
                return p["samples_merged"] == TOTAL and p["tiles_done"] == TILES

            wait_until(merged_in_memory, 300, "every sample merged in memory")
            assert client.get(job["id"])["state"] == "running"
            assert not client.ready()
            wait_until(
                lambda: client.get(long["id"])["progress"]["samples_merged"] > 0,
                60,
                "the second job to merge samples",
            )
            long_merged = client.get(long["id"])["progress"]["samples_merged"]
        farm.server.send_signal(signal.SIGTERM)
        assert farm.server.wait(timeout=60) == 0
        stop_processes(farm.worker_procs)  # from here on nothing is rendered
        log = (data / "server.log").read_text()
        assert "could not write the last checkpoint" not in log
        assert "kept the unsaved state of 2 jobs" in log  # not the stored first one
        (spooled,) = (data / "spool").iterdir()
        kept = spooled.read_bytes()
        farm.start_server()  # starts the embedded database again
        with Client(farm.url) as client:
            view = client.get(job["id"])
            assert view["state"] == "completed"
            assert view["progress"]["samples_merged"] == TOTAL
            assert_identical(images_of(client, job["id"], tmp_path), expected)
            resumed = client.get(long["id"])
            assert resumed["state"] == "running"
            assert resumed["progress"]["samples_merged"] >= long_merged
            assert metric(farm.url, "renderfarm_samples_merged_total") == 0
            events = client.events(job["id"])
        assert not list((data / "spool").iterdir())
        assert finished_events(data)[job["id"]] == 1
        assert "replayed the spool" in (data / "server.log").read_text()
        # A server that crashed after replaying the spool but before deleting it replays it
        # again at its next start: nothing changes.
        farm.server.send_signal(signal.SIGTERM)
        assert farm.server.wait(timeout=60) == 0
        spooled.write_bytes(kept)
        farm.start_server()
        with Client(farm.url) as client:
            assert client.events(job["id"]) == events
            assert client.get(job["id"])["progress"] == view["progress"]
            assert_identical(images_of(client, job["id"], tmp_path), expected)
            again = client.get(long["id"])["progress"]["samples_merged"]
            assert again == resumed["progress"]["samples_merged"]
            assert client.cancel(long["id"])["state"] == "cancelled"
        assert not list((data / "spool").iterdir())


def test_every_api_answers_503_or_unavailable_while_the_database_is_down(tmp_path):
    """With the database stopped, every REST endpoint that needs it answers 503 with
    Retry-After and the usual error body, and every such gRPC method UNAVAILABLE (quickly, not
    after a long wait); once the database is back they work again and nothing was half-stored."""
    data = tmp_path / "farm"
    pgdata = data / "pg"
    tiny = {"width": 16, "height": 16, "tile_size": 16, "max_spp": 4}
    with LocalFarm(workers=0, data_dir=data) as farm, Client(farm.url) as client:
        job = client.submit(CORNELL, settings=tiny, name="before")
        sha = job["scene_sha256"]
        assert client.cancel(job["id"])["state"] == "cancelled"
        pg_ctl(pgdata, "stop", "-m", "fast", "-w")
        try:
            wait_until(lambda: not client.ready(), 30, "the server to report unready")
            unknown = "ffffffffffff"
            requests = [
                ("POST", "/api/v1/jobs", {"json": {"scene_sha256": sha, "settings": tiny}}),
                ("POST", "/api/v1/jobs", {"files": {"scene": ("box.glb", pack_gltf(CORNELL))}}),
                ("GET", "/api/v1/jobs", {}),
                ("GET", f"/api/v1/jobs/{unknown}", {}),
                ("POST", f"/api/v1/jobs/{unknown}/cancel", {}),
                ("DELETE", f"/api/v1/jobs/{job['id']}", {}),
                ("GET", f"/api/v1/jobs/{job['id']}/events", {}),
                ("GET", f"/api/v1/jobs/{unknown}/convergence", {}),
                ("GET", f"/api/v1/jobs/{unknown}/watch", {}),
                ("GET", f"/api/v1/jobs/{unknown}/image.png", {}),
                ("GET", f"/api/v1/scenes/{sha}", {}),
            ]
            with httpx.Client(base_url=farm.url, timeout=30) as http:
                for method, path, kwargs in requests:
                    started = time.monotonic()
                    r = http.request(method, path, **kwargs)
                    took = time.monotonic() - started
                    assert r.status_code == 503, (method, path, r.status_code, r.text)
                    assert int(r.headers["retry-after"]) >= 1, (method, path)
                    assert r.json()["field"] == "database", (method, path)
                    assert "database" in r.json()["detail"], (method, path)
                    assert took < 5, f"{method} {path} took {took:.1f} s"
            with grpc.insecure_channel(farm.grpc_address) as channel:
                jobs = jobs_pb2_grpc.JobServiceStub(channel)
                scenes = scenes_pb2_grpc.SceneServiceStub(channel)
                calls = [
                    (jobs.SubmitJob, jobs_pb2.SubmitJobRequest(scene_sha256=sha)),
                    (jobs.ListJobs, jobs_pb2.ListJobsRequest()),
                    (jobs.GetJob, jobs_pb2.GetJobRequest(job_id=unknown)),
                    (jobs.CancelJob, jobs_pb2.CancelJobRequest(job_id=unknown)),
                    (jobs.DeleteJob, jobs_pb2.DeleteJobRequest(job_id=job["id"])),
                    (jobs.GetImage, jobs_pb2.GetImageRequest(job_id=unknown)),
                    (scenes.GetScene, scenes_pb2.GetSceneRequest(sha256=sha)),
                    (lambda r, timeout: list(jobs.WatchJob(r, timeout=timeout)),
                     jobs_pb2.WatchJobRequest(job_id=unknown)),
                ]  # fmt: skip
                for call, request in calls:
                    try:
                        call(request, timeout=30)
                    except grpc.RpcError as e:
                        assert e.code() == grpc.StatusCode.UNAVAILABLE, (request, e)
                        trailing = dict(e.trailing_metadata() or ())
                        assert trailing["renderfarm-field"] == "database"
                        assert int(trailing["retry-after"]) >= 1
                    else:
                        raise AssertionError(f"{type(request).__name__} answered")
        finally:
            pg_ctl(pgdata, "start", "-w", "-l", str(pgdata / "log"), "-o", f'-h "" -k {pgdata}')
        wait_until(client.ready, 60, "the server to be ready again")
        listed = client.list(page_size=50)["jobs"]
        assert [j["name"] for j in listed] == ["before"]  # nothing half-stored
        client.delete(job["id"])
        assert client.list(page_size=50)["jobs"] == []


# --------------------------------------------------------------------------- load
BURST_PROCESSES = 20
BURST_PER_PROCESS = 25
BURST_SETTINGS = {"width": 16, "height": 16, "tile_size": 16, "max_spp": 4, "noise_threshold": 0}


def every_job(client: Client, state: str = "") -> list[dict]:
    """Every job in the list, page after page (at most 10 pages of 500)."""
    jobs, token = [], ""
    for _ in range(10):
        page = client.list(state=state, page_size=500, page_token=token)
        jobs += page["jobs"]
        token = page["next_page_token"]
        if not token:
            return jobs
    raise AssertionError("more than 10 pages of jobs")


def _submit_burst(url: str, sha: str, index: int, barrier, results) -> None:
    """One client process: wait for the others, then submit BURST_PER_PROCESS jobs at once
    (one thread each); put (name, status, Retry-After, body) of every answer on `results`."""
    from concurrent.futures import ThreadPoolExecutor

    with httpx.Client(base_url=url, timeout=120, limits=httpx.Limits(max_connections=100)) as c:

        def submit(i: int):
            name = f"p{index}-{i}"
            body = {"scene_sha256": sha, "settings": BURST_SETTINGS, "name": name}
            try:
                r = c.post("/api/v1/jobs", json=body)
            except httpx.HTTPError as e:
                return name, -1, None, repr(e)
            try:
                answer = r.json()
            except ValueError:
                answer = r.text  # not the error body every answer must have
            return name, r.status_code, r.headers.get("retry-after"), answer

        barrier.wait(timeout=120)
        with ThreadPoolExecutor(BURST_PER_PROCESS) as pool:
            answers = list(pool.map(submit, range(BURST_PER_PROCESS)))
    results.put(answers)


def test_500_concurrent_submissions_get_201_or_a_documented_refusal_and_run_once(tmp_path):
    """500 submissions at once from 20 client processes: every answer is 201, or 429/503 with
    Retry-After and the error body (never another 5xx); every accepted job completes exactly
    once, and no refused one was stored."""
    data = tmp_path / "farm"
    with LocalFarm(workers=2, data_dir=data, threads=1) as farm, Client(farm.url) as client:
        first = client.submit(CORNELL, settings=BURST_SETTINGS, name="upload")
        ctx = multiprocessing.get_context("spawn")
        barrier = ctx.Barrier(BURST_PROCESSES + 1)
        results = ctx.Queue()
        procs = [
            ctx.Process(
                target=_submit_burst, args=(farm.url, first["scene_sha256"], n, barrier, results)
            )
            for n in range(BURST_PROCESSES)
        ]
        for p in procs:
            p.start()
        try:
            barrier.wait(timeout=120)  # every process is ready: the burst starts now
            started = time.monotonic()
            answers = [a for _ in procs for a in results.get(timeout=300)]
            burst_s = time.monotonic() - started
        finally:
            for p in procs:
                p.join(timeout=60)
                if p.is_alive():
                    p.kill()
        statuses: dict[int, int] = {}
        for name, status, retry_after, body in answers:
            statuses[status] = statuses.get(status, 0) + 1
            assert status in (201, 429, 503), (name, status, body)
            if status != 201:
                assert retry_after is not None and int(retry_after) >= 1, (name, status)
                assert set(body) == {"detail", "field"} and body["detail"], (name, body)
        accepted = {body["id"]: name for name, status, _, body in answers if status == 201}
        print(f"burst of {len(answers)} answered in {burst_s:.1f} s: {statuses}")
        assert len(answers) == BURST_PROCESSES * BURST_PER_PROCESS
        assert len(accepted) == statuses.get(201, 0)  # distinct ids
        # The queue is sized for this burst (RENDERFARM_DB_QUEUE): nobody was turned away.
        assert statuses.get(429, 0) == 0

        wait_until(
            lambda: len(every_job(client, "completed")) == len(accepted) + 1,
            240,
            "every accepted job to complete",
            poll_s=0.5,
        )
        completed_s = time.monotonic() - started
        print(f"all {len(accepted)} accepted jobs completed {completed_s:.1f} s after the burst")
        listed = every_job(client)
        assert len(listed) == len(accepted) + 1  # nothing refused was stored
        for job in listed:
            assert job["state"] == "completed"
            assert job["progress"]["samples_merged"] == 16 * 16 * 4
            if job["id"] != first["id"]:
                assert accepted[job["id"]] == job["name"]
        finishes = finished_events(data)
        assert sorted(finishes) == sorted([*accepted, first["id"]])
        assert set(finishes.values()) == {1}
