"""Fault injection: nothing a user submitted and nothing a worker finished is lost or counted
twice when workers, the server or the database fail (docs/operations.md, "Reliability").

Every test renders a fixed number of samples (noise_threshold 0), so the undisturbed image is
known independently: the standalone `renderfarm-worker render` of the same settings and seed,
which the farm equals to float32 rounding (tests/test_end_to_end.py). A worker cut off the
network is covered by tests/test_deploy_multihost.py, which cuts a worker's veth link.
"""

from __future__ import annotations

import signal
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import psycopg
import pytest

from renderfarm.cli.localfarm import LocalFarm
from renderfarm.client import Client
from renderfarm.domain import channels
from renderfarm.infra.embedded_db import EmbeddedPostgres, pg_ctl
from renderfarm.infra.images import read_exr

from .conftest import CORNELL
from .mattes import matte
from .scrape import metric
from .waiting import wait_until

# Long enough (about 9.4M samples) that a fault injected a second after a fraction of the job
# merged still lands mid-job on a fast renderer: at 256 spp two one-thread workers finished the
# whole job within that second, and the server-kill test killed a finished job.
SPP = 1024
TOTAL = 96 * 96 * SPP
SETTINGS = {"width": 96, "height": 96, "tile_size": 16, "max_spp": SPP, "noise_threshold": 0}
SETTINGS |= {"seed": 21}
# The outputs the server-kill test's job renders beside the image (settings.aovs).
OUTPUTS = ["depth", "ids", "cryptomatte", "lobes", "light_groups"]
FAST_LEASES = {
    "RENDERFARM_LEASE_S": "2",
    "RENDERFARM_HEARTBEAT_INTERVAL_S": "0.5",
    "RENDERFARM_CHECKPOINT_INTERVAL_S": "0.5",
}


@pytest.fixture(scope="module")
def reference(worker_binary, tmp_path_factory) -> np.ndarray:
    out = tmp_path_factory.mktemp("ref") / "alone.exr"
    args = [worker_binary, "render", str(CORNELL), "-o", str(out), "--threads", "2"]
    args += ["--width", "96", "--height", "96", "--spp", str(SPP), "--seed", "21"]
    subprocess.run(args, check=True, capture_output=True, timeout=600)
    return rgb(out)


def rgb(path) -> np.ndarray:
    ch = read_exr(str(path))
    return np.stack([ch["R"], ch["G"], ch["B"]], axis=-1)


AOV_CHANNELS = ("albedo.R", "albedo.G", "albedo.B", "normal.X", "normal.Y", "normal.Z")


def aovs(path) -> np.ndarray:
    ch = read_exr(str(path))
    return np.stack([ch[name] for name in AOV_CHANNELS], axis=-1)


def farm_image(client: Client, job_id: str, tmp_path: Path) -> np.ndarray:
    path = tmp_path / f"{job_id}.exr"
    path.write_bytes(client.image(job_id, "exr"))
    return rgb(path)


def assert_same_image(image: np.ndarray, reference: np.ndarray) -> None:
    np.testing.assert_allclose(image, reference, rtol=1e-6, atol=1e-7)


def database_url(data: Path) -> str:
    """The embedded PostgreSQL of the farm in `data` (it outlives a killed server)."""
    return f"postgresql://postgres:@/postgres?host={data / 'pg'}"


def checkpointed_samples(data: Path, job_id: str) -> int:
    """Pixel samples of the job's tiles in the database: what a restart resumes from (SETTINGS'
    tiles are all 16 x 16; the tiles table holds each tile's samples per pixel)."""
    with psycopg.connect(database_url(data)) as conn:
        (spp,) = conn.execute(
            "SELECT coalesce(sum(samples), 0) FROM tiles WHERE job_id = %s", (job_id,)
        ).fetchone()
    return spp * 16 * 16


def checkpointed_while_stopped(data: Path, job_id: str) -> int:
    """checkpointed_samples of a farm whose server has exited, stopping its embedded
    PostgreSQL: the cluster is started for the query and stopped again."""
    db = EmbeddedPostgres(data)
    db.start()
    try:
        return checkpointed_samples(data, job_id)
    finally:
        db.stop()


def other_sessions(data: Path) -> int:
    """Client sessions of the farm's embedded PostgreSQL other than this query's own: those
    of a killed server end once PostgreSQL sees its sockets closed (a commit it had sent is
    carried out first), and from then on nothing changes its checkpoints."""
    with psycopg.connect(database_url(data)) as conn:
        (n,) = conn.execute(
            "SELECT count(*) FROM pg_stat_activity"
            " WHERE backend_type = 'client backend' AND pid <> pg_backend_pid()"
        ).fetchone()
    return n


def planned_tiles(data: Path, job_id: str) -> int:
    """The job's checkpointed tiles that hold planned batch sizes."""
    with psycopg.connect(database_url(data)) as conn:
        (planned,) = conn.execute(
            "SELECT count(*) FROM tiles WHERE job_id = %s AND batch_plan IS NOT NULL", (job_id,)
        ).fetchone()
    return planned


def merged_fraction(client: Client, job_id: str) -> float:
    p = client.get(job_id)["progress"]
    return p["samples_merged"] / TOTAL


def submit_when_two_workers(client: Client, until_merged: float, **more) -> dict:
    """Wait for both workers, submit the SETTINGS job (with `more` settings), and wait until
    that fraction of its samples is merged."""
    wait_until(lambda: len(client.workers()) == 2, 30, "two workers")
    job = client.submit(CORNELL, settings={**SETTINGS, **more})
    wait_until(
        lambda: merged_fraction(client, job["id"]) > until_merged,
        300,
        f"{until_merged:.0%} merged",
    )
    return job


def test_kill_9_one_of_two_workers_mid_job(tmp_path, reference):
    """A worker killed outright loses only its in-flight batches; they are re-leased and the
    image equals an undisturbed render."""
    with LocalFarm(workers=2, data_dir=tmp_path / "farm", threads=1, env=FAST_LEASES) as farm:
        with Client(farm.url) as client:
            job = submit_when_two_workers(client, until_merged=0.2)
            victim = farm.worker_procs[0]
            victim.send_signal(signal.SIGKILL)
            victim.wait(timeout=10)
            job = client.wait(job["id"], poll_s=0.2, timeout_s=600)
            assert job["state"] == "completed"
            assert job["progress"]["samples_merged"] == TOTAL
            assert len(client.workers()) == 1
            assert_same_image(farm_image(client, job["id"], tmp_path), reference)


def test_kill_9_server_resumes_from_checkpoint_without_rendering_it_again(
    tmp_path, reference, worker_binary
):
    """The server is killed outright mid-job and started again: the job resumes from its last
    checkpoint, finishes with the same image, and exactly the samples that were not
    checkpointed are rendered again (counted by the restarted server's own metrics)."""
    with LocalFarm(workers=2, data_dir=tmp_path / "farm", threads=1, env=FAST_LEASES) as farm:
        with Client(farm.url) as client:
            job = submit_when_two_workers(client, until_merged=0.4, aovs=OUTPUTS)
            merged = client.get(job["id"])["progress"]["samples_merged"]
            # Checkpoints come every 0.5 s: wait for one holding what is merged by now.
            wait_until(
                lambda: checkpointed_samples(farm.data_dir, job["id"]) >= merged,
                30,
                f"a checkpoint of the {merged} samples merged",
                poll_s=0.1,
            )
            merged_before_crash = client.get(job["id"])["progress"]["samples_merged"]
            assert merged_before_crash < TOTAL, "the job finished before the server was killed"
        farm.server.send_signal(signal.SIGKILL)
        farm.server.wait(timeout=10)
        # The restart resumes from what the database held when the server died: read it
        # before the restart, not from the restarted server's first answer. Workers reconnect
        # to its gRPC port, which opens before its HTTP API, so by that answer it may have
        # merged new batches (issue 39: 14 of 64 spp, 229,376 samples counted as checkpointed).
        wait_until(lambda: other_sessions(farm.data_dir) == 0, 30, "the killed server's sessions")
        checkpointed = checkpointed_samples(farm.data_dir, job["id"])
        # The checkpoint seen before the crash survived it; checkpoints come every 0.5 s, so
        # most merged work survived, and some was left to render.
        assert merged <= checkpointed < TOTAL
        assert 0.5 * merged_before_crash <= checkpointed
        farm.start_server()
        with Client(farm.url) as client:
            resumed = client.get(job["id"])
            assert resumed["state"] == "running"
            # Resumed from that checkpoint, plus whatever it merged since it started.
            since_start = metric(farm.url, "renderfarm_samples_merged_total")
            assert checkpointed <= resumed["progress"]["samples_merged"]
            assert resumed["progress"]["samples_merged"] <= checkpointed + since_start
            job = client.wait(job["id"], poll_s=0.2, timeout_s=600)
            assert job["state"] == "completed"
            total = TOTAL
            assert job["progress"]["samples_merged"] == total
            # Exactly what was not checkpointed is rendered again (the restarted server's own
            # count of merged samples): no checkpointed batch twice; one merged twice would
            # also change the count above or the image below.
            rendered_after_restart = metric(farm.url, "renderfarm_samples_merged_total")
            assert rendered_after_restart == total - checkpointed
            assert_same_image(farm_image(client, job["id"], tmp_path), reference)
            # The albedo and normal layers (each pixel's first 16 samples, checkpointed apart
            # from the statistics) survived the crash: they equal a standalone 16-spp render's.
            farm_exr = tmp_path / f"{job['id']}.exr"  # written by farm_image
            # Every output layer (first-sample depth and labels, Cryptomatte's ranked counts
            # and the lobes' and light groups' sums over every sample) survived it too: the same
            # bits as the same job undisturbed.
            twin = client.submit(CORNELL, settings={**SETTINGS, "aovs": OUTPUTS})
            twin = client.wait(twin["id"], poll_s=0.2, timeout_s=600)
            assert twin["state"] == "completed"
            twin_exr = tmp_path / "twin.exr"
            client.save_image(twin["id"], twin_exr, "exr")
            crashed, calm = read_exr(str(farm_exr)), read_exr(str(twin_exr))
            lobes = tuple(f"{lobe}." for lobe, *_ in channels.LOBES)
            outputs = [c for c in calm if c.startswith(("depth", "instance", "material",
                                                         "Crypto", "light_group_",
                                                         *lobes))]  # fmt: skip
            # The Cornell box's light groups: its emissive quad `light`, and the environment.
            assert len(outputs) == 1 + 2 + 3 * 3 * 4 + 8 * 3 + 2 * 3
            for c in outputs:
                assert np.array_equal(crashed[c], calm[c]), c
            assert matte(calm, "CryptoObject", "red").max() == 1.0  # the red wall: not vacuous
    # The restarted server stopped the embedded PostgreSQL that outlived the killed one.
    assert not (tmp_path / "farm" / "pg" / "postmaster.pid").exists()
    assert_aovs_of_the_first_16_samples(farm_exr, worker_binary, tmp_path)


def assert_aovs_of_the_first_16_samples(farm_exr: Path, worker_binary: str, tmp_path: Path):
    """The farm's albedo and normal layers equal a standalone 16-spp render's."""
    alone = tmp_path / "alone16.exr"
    args = [worker_binary, "render", str(CORNELL), "-o", str(alone), "--threads", "2"]
    args += ["--width", "96", "--height", "96", "--spp", "16", "--seed", "21"]
    subprocess.run(args, check=True, capture_output=True, timeout=600)
    expected = aovs(alone)
    assert np.abs(expected).max() > 0.1
    np.testing.assert_allclose(aovs(farm_exr), expected, rtol=1e-5, atol=1e-6)


def test_kill_9_server_mid_plan_resumes_the_planned_batches(tmp_path):
    """An adaptive job whose tiles are in their planned batches (sizes planned from each tile's
    noise, tiling.plan_batch) when the server is killed resumes with the saved plans: it ends
    with the image and the per-tile stops of the same job rendered without a crash."""
    settings = {**SETTINGS, "noise_threshold": 0.05, "max_spp": 2048}
    data = tmp_path / "farm"
    with LocalFarm(workers=2, data_dir=data, threads=1, env=FAST_LEASES) as farm:
        with Client(farm.url) as client:
            wait_until(lambda: len(client.workers()) == 2, 30, "two workers")
            ref = client.wait(client.submit(CORNELL, settings=settings)["id"], timeout_s=600)
            assert ref["state"] == "completed"
            total = ref["progress"]["samples_merged"]
            job = client.submit(CORNELL, settings=settings)
            wait_until(
                lambda: client.get(job["id"])["progress"]["samples_merged"] > 0.4 * total,
                300,
                "40% of the samples merged",
            )
            # A checkpoint (every 0.5 s) holding planned batches, before the kill.
            wait_until(
                lambda: planned_tiles(data, job["id"]), 30, "planned batches checkpointed", 0.1
            )
            assert client.get(job["id"])["state"] == "running"
        farm.server.send_signal(signal.SIGKILL)
        farm.server.wait(timeout=10)
        # The database outlives the killed server: the checkpoint holds planned batches.
        assert planned_tiles(data, job["id"]) > 0
        farm.start_server()
        with Client(farm.url) as client:
            job = client.wait(job["id"], poll_s=0.2, timeout_s=600)
            assert job["state"] == "completed"
            assert job["stops"] == ref["stops"]
            assert_same_image(
                farm_image(client, job["id"], tmp_path), farm_image(client, ref["id"], tmp_path)
            )


def test_checkpoints_from_before_the_aov_split_resume_and_are_rewritten(
    tmp_path, reference, worker_binary
):
    """A job checkpointed in the old format (all six arrays in `accumulators`, float64, no
    `aovs`, no coverage) resumes with its albedo and normal intact, and its tiles are written
    again in the new format (statistics and coverage, and AOVs apart)."""
    data = tmp_path / "farm"
    with LocalFarm(workers=2, data_dir=data, threads=1, env=FAST_LEASES) as farm:
        with Client(farm.url) as client:
            job = submit_when_two_workers(client, until_merged=0.3)
        farm.server.send_signal(signal.SIGTERM)
        assert farm.server.wait(timeout=60) == 0
        # Rewrite the checkpoints as the previous format stored them.
        db = EmbeddedPostgres(data)
        url = db.start()
        try:
            with psycopg.connect(url, autocommit=True) as conn:
                rows = conn.execute(
                    "SELECT tile_index, accumulators, aovs FROM tiles WHERE job_id = %s",
                    (job["id"],),
                ).fetchall()
                assert rows and all(aov is not None for _, _, aov in rows)
                pixels = 16 * 16
                for index, stats, aov in rows:
                    # The float64 statistics without the float32 coverage that now ends them,
                    # and without the blobs' headers (channels.blob_header).
                    stats = bytes(stats)[channels.read_header(stats, "stats")[3] :]
                    aov = bytes(aov)[channels.read_header(aov, "aovs")[3] :]
                    old_stats = stats[: pixels * 6 * 8]
                    legacy = old_stats + np.frombuffer(aov, "<f4").astype("<f8").tobytes()
                    conn.execute(
                        "UPDATE tiles SET accumulators = %s, aovs = NULL"
                        " WHERE job_id = %s AND tile_index = %s",
                        (legacy, job["id"], index),
                    )
        finally:
            db.stop()
        farm.start_server()
        with Client(farm.url) as client:
            job = client.wait(job["id"], poll_s=0.2, timeout_s=600)
            assert job["state"] == "completed"
            assert_same_image(farm_image(client, job["id"], tmp_path), reference)
            farm_exr = tmp_path / f"{job['id']}.exr"  # written by farm_image
            url = f"postgresql://postgres:@/postgres?host={data / 'pg'}"
            with psycopg.connect(url) as conn:
                blobs = conn.execute(
                    "SELECT accumulators, aovs FROM tiles WHERE job_id = %s", (job["id"],)
                ).fetchall()
    # Written again in today's format: blobs with a header naming their arrays, the statistics
    # and coverage (6 float64 and 1 float32 a pixel) apart from the AOVs (6 float32).
    pixels = 16 * 16
    assert blobs
    for stats, aovs in blobs:
        for blob, names, per_pixel in ((stats, channels.STATS_ARRAYS, 6 * 8 + 4),
                                       (aovs, channels.WINDOWED_ARRAYS, 6 * 4)):  # fmt: skip
            _, arrays, blob_pixels, offset = channels.read_header(blob, "tile")
            assert tuple(a.name for a in arrays) == names and blob_pixels == pixels
            assert len(blob) - offset == pixels * per_pixel
    assert_aovs_of_the_first_16_samples(farm_exr, worker_binary, tmp_path)


def test_database_restart_mid_job_loses_nothing(tmp_path):
    """PostgreSQL stops mid-job: the server keeps merging, reports unready, and once the
    database is back it catches up; the job, every merged sample, its tiles and its events
    are all stored. (A long job at low resolution, so it is still running when the database
    goes away; whether it is still running or has finished by the time the server notices the
    outage depends on the renderer's speed, and both must be caught up on.)"""
    # ~50 s of rendering for two one-thread workers on this project's CI machine; the database
    # goes away at 2%, so a stop that is slow on a busy machine still finds the job running.
    settings = {"width": 48, "height": 48, "tile_size": 16, "max_spp": 49152, "noise_threshold": 0}
    total = 48 * 48 * 49152
    data = tmp_path / "farm"
    with LocalFarm(workers=2, data_dir=data, threads=1, env=FAST_LEASES) as farm:
        with Client(farm.url) as client:
            wait_until(lambda: len(client.workers()) == 2, 30, "two workers")
            job = client.submit(CORNELL, settings=settings)

            def merged() -> int:
                return client.get(job["id"])["progress"]["samples_merged"]

            wait_until(lambda: merged() > 0.02 * total, 300, "2% merged")
            at_2_percent = time.monotonic()
            pgdata = data / "pg"
            pg_ctl(pgdata, "stop", "-m", "fast", "-w")
            try:
                during = merged()
                assert during < total, (
                    f"the job ended before the database went away: it merged the last 98% in"
                    f" under {time.monotonic() - at_2_percent:.1f} s"
                )
                wait_until(lambda: merged() > during, 60, "merging to go on without the database")
                wait_until(lambda: not client.ready(), 30, "the server to report unready")
            finally:
                pg_ctl(pgdata, "start", "-w", "-l", str(pgdata / "log"),
                        "-o", f'-h "" -k {pgdata}')  # fmt: skip
            wait_until(client.ready, 60, "the server to be ready again")
            job = client.wait(job["id"], poll_s=0.2, timeout_s=600)
            assert job["state"] == "completed"
            assert job["progress"]["samples_merged"] == total
        url = f"postgresql://postgres:@/postgres?host={data / 'pg'}"

        def stored():
            with psycopg.connect(url) as conn:
                state = conn.execute("SELECT state FROM jobs WHERE id = %s", (job["id"],))
                tiles = conn.execute(
                    "SELECT count(*), min(samples) FROM tiles WHERE job_id = %s", (job["id"],)
                ).fetchone()
                kinds = {
                    k
                    for (k,) in conn.execute(
                        "SELECT kind FROM events WHERE job_id = %s", (job["id"],)
                    )
                }
                return state.fetchone()[0], tiles, kinds

        state, (tiles, min_samples), kinds = wait_until(
            lambda: stored() if stored()[0] == "completed" else None, 30, "the final state stored"
        )
        assert tiles == 9 and min_samples == settings["max_spp"]
        assert {"job_submitted", "job_started", "tile_stopped", "job_finished"} <= kinds
    # The server stops the cluster it was given back (started by pg_ctl, not by pgserver).
    assert not (data / "pg" / "postmaster.pid").exists()


def test_frozen_worker_loses_its_leases_and_its_late_results_change_nothing(tmp_path, reference):
    """A worker stopped with SIGSTOP past its lease: its tasks are re-leased; after SIGCONT its
    late results are discarded (or merged once, with the re-leased copy cancelled)."""
    with LocalFarm(workers=2, data_dir=tmp_path / "farm", threads=1, env=FAST_LEASES) as farm:
        with Client(farm.url) as client:
            job = submit_when_two_workers(client, until_merged=0.2)
            expired = metric(farm.url, "renderfarm_leases_expired_total")
            frozen = farm.worker_procs[0]
            frozen.send_signal(signal.SIGSTOP)
            try:
                # Its heartbeats stop: its leases (2 s) run out and their batches are re-queued.
                try:
                    wait_until(
                        lambda: metric(farm.url, "renderfarm_leases_expired_total") > expired,
                        30,
                        "the frozen worker's leases to expire",
                        poll_s=0.2,
                    )
                except AssertionError as e:  # what the server saw of the workers meanwhile
                    raise AssertionError(f"{e}; workers: {client.workers()}") from None
                before = client.get(job["id"])["progress"]["samples_merged"]
                wait_until(
                    lambda: client.get(job["id"])["progress"]["samples_merged"] > before,
                    60,
                    "the other worker to carry on with the re-leased work",
                )
            finally:
                frozen.send_signal(signal.SIGCONT)
            job = client.wait(job["id"], poll_s=0.2, timeout_s=600)
            assert job["state"] == "completed"
            assert job["progress"]["samples_merged"] == TOTAL
            assert_same_image(farm_image(client, job["id"], tmp_path), reference)


def test_fifty_concurrent_jobs_from_several_clients_all_complete_once(tmp_path):
    """50 submissions from 5 concurrent clients: 50 distinct jobs, every one completed with
    every sample, none lost and none duplicated."""
    small = {"width": 16, "height": 16, "tile_size": 8, "max_spp": 2, "noise_threshold": 0}
    with LocalFarm(workers=2, data_dir=tmp_path / "farm", threads=1) as farm:
        submitted: list[str] = []
        errors: list[BaseException] = []
        lock = threading.Lock()

        def client_thread(n: int) -> None:
            try:
                with Client(farm.url) as client:
                    for i in range(10):
                        job = client.submit(CORNELL, settings=small, name=f"c{n}-{i}")
                        with lock:
                            submitted.append(job["id"])
            except BaseException as e:  # reported below, in the test's thread
                errors.append(e)

        threads = [threading.Thread(target=client_thread, args=(n,)) for n in range(5)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout=300)
        assert not errors, errors
        assert len(submitted) == 50 and len(set(submitted)) == 50
        with Client(farm.url) as client:
            for job_id in submitted:
                job = client.wait(job_id, poll_s=0.2, timeout_s=300)
                assert job["state"] == "completed"
                assert job["progress"]["samples_merged"] == 16 * 16 * 2
            listed = client.list(page_size=500)["jobs"]
            assert sorted(j["id"] for j in listed) == sorted(submitted)
            assert sorted(j["name"] for j in listed) == sorted(
                f"c{n}-{i}" for n in range(5) for i in range(10)
            )


def test_graceful_shutdown_drains_and_loses_nothing(tmp_path, reference):
    """SIGTERM mid-job: the server stops leasing, waits for the tasks in flight, writes a last
    checkpoint and exits 0; started again, it resumes with everything merged before the
    shutdown and renders only the rest."""
    with LocalFarm(workers=2, data_dir=tmp_path / "farm", threads=1, env=FAST_LEASES) as farm:
        with Client(farm.url) as client:
            job = submit_when_two_workers(client, until_merged=0.3)
            seen = client.get(job["id"])["progress"]["samples_merged"]
        farm.server.send_signal(signal.SIGTERM)
        assert farm.server.wait(timeout=60) == 0
        log = (tmp_path / "farm" / "server.log").read_text()
        assert "draining" in log
        # What the restart resumes from, read before it (as in the server-kill test: by the
        # restarted server's first answer, reconnected workers may have merged more).
        checkpointed = checkpointed_while_stopped(tmp_path / "farm", job["id"])
        assert seen <= checkpointed < TOTAL  # the last checkpoint has all merged before exit
        farm.start_server()
        with Client(farm.url) as client:
            resumed = client.get(job["id"])["progress"]["samples_merged"]
            assert checkpointed <= resumed
            job = client.wait(job["id"], poll_s=0.2, timeout_s=600)
            assert job["state"] == "completed"
            total = TOTAL
            assert metric(farm.url, "renderfarm_samples_merged_total") == total - checkpointed
            assert_same_image(farm_image(client, job["id"], tmp_path), reference)


def test_a_newer_database_schema_refuses_to_start_the_server(tmp_path):
    """Migrations are numbered; a database migrated by a newer server is not touched."""
    data = tmp_path / "farm"
    with LocalFarm(workers=0, data_dir=data):
        pass  # creates and migrates the embedded database, then stops
    from renderfarm.infra.embedded_db import EmbeddedPostgres

    pg = EmbeddedPostgres(data)
    url = pg.start()
    try:
        with psycopg.connect(url, autocommit=True) as conn:
            conn.execute("INSERT INTO schema_migrations (version, name) VALUES (999, 'future')")
    finally:
        pg.stop()
    import sys

    done = subprocess.run(
        [sys.executable, "-m", "renderfarm", "server", "--data-dir", str(data)]
        + ["--http-port", "0", "--grpc-port", "0"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert done.returncode == 1
    assert "schema is version 999, newer than this server knows" in done.stderr
