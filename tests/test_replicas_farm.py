"""Two `renderfarm server` processes over one PostgreSQL form one farm (#39): a job submitted to
server A, which A renders with its worker, moves to server B when A is killed with SIGKILL, within
the bound docs/architecture.md gives ("Ownership, leases and fencing": the job lease, 8 s, and
a quarter of it), resumes from A's last checkpoint, and ends with the tiles of an undisturbed
run of the same job, bit for bit. One worker serves both servers (`renderfarm-worker connect
--server A,B`), as a farm's workers serve its replicas: it renders the job for A, then for B."""

from __future__ import annotations

import signal
import time

import psycopg
import pytest

from renderfarm.cli.localfarm import LocalFarm, spawn_workers, stop_processes
from renderfarm.client import Client
from renderfarm.infra.embedded_db import EmbeddedPostgres

from .conftest import CORNELL
from .waiting import wait_until

SETTINGS = {"width": 64, "height": 64, "tile_size": 16, "max_spp": 512, "noise_threshold": 0}
SETTINGS |= {"seed": 5}
TOTAL = 64 * 64 * 512
TAKEOVER_S = 15.0  # the bound; with the default 8 s lease it is 8 + 2 s and a resume
FAST = {
    "RENDERFARM_LEASE_S": "2",
    "RENDERFARM_HEARTBEAT_INTERVAL_S": "0.5",
    "RENDERFARM_CHECKPOINT_INTERVAL_S": "0.5",
}


@pytest.fixture()
def database(tmp_path):
    db = EmbeddedPostgres(tmp_path / "db")
    url = db.start()
    try:
        yield url
    finally:
        db.stop()


def tiles(url: str, job_id: str) -> list[tuple]:
    with psycopg.connect(url) as conn:
        return conn.execute(
            "SELECT tile_index, samples, batches, accumulators, aovs, stop_batch, stop_reason"
            " FROM tiles WHERE job_id = %s ORDER BY tile_index",
            (job_id,),
        ).fetchall()


def checkpointed(url: str, job_id: str) -> int:
    return sum(t[1] for t in tiles(url, job_id)) * 16 * 16


def test_kill_9_of_one_of_two_servers_moves_its_job_to_the_other(tmp_path, database):
    env = {"RENDERFARM_DATABASE_URL": database, **FAST}
    a = LocalFarm(workers=0, data_dir=tmp_path / "a", env={**env, "RENDERFARM_REPLICA_ID": "A"})
    b = LocalFarm(workers=0, data_dir=tmp_path / "b", env={**env, "RENDERFARM_REPLICA_ID": "B"})
    with a, b, Client(a.url) as at_a, Client(b.url) as at_b:
        worker = spawn_workers(1, f"{a.grpc_address},{b.grpc_address}", threads=1,
                               log_dir=tmp_path)  # fmt: skip
        try:
            moved, took, done, replicas, again = _kill_a_mid_job(database, a, at_a, at_b)
        finally:
            stop_processes(worker)
    assert took <= TAKEOVER_S, f"B took the job {took:.1f} s after A was killed"
    assert done["state"] == "completed" and done["progress"]["samples_merged"] == TOTAL
    assert tiles(database, moved) == tiles(database, again)
    assert set(replicas) == {"A", "B"}
    assert replicas["B"]["live"] and replicas["B"]["jobs_owned"] == 0  # released once done
    assert replicas["A"]["jobs_owned"] == 0


def _kill_a_mid_job(database: str, a: LocalFarm, at_a: Client, at_b: Client) -> tuple:
    """Submit to A, kill it with SIGKILL after a checkpoint of a fifth, wait for B to hold the
    job and complete it, then render it undisturbed on B."""
    wait_until(lambda: len(at_a.workers()) == 1 and len(at_b.workers()) == 1, 60, "worker")
    job = at_a.submit(CORNELL, settings=SETTINGS, name="moved")["id"]
    assert at_b.get(job)["replica"] == "A"  # B answers for it: A owns it
    wait_until(lambda: checkpointed(database, job) > 0.2 * TOTAL, 300, "a checkpoint of 20%")
    a.server.send_signal(signal.SIGKILL)
    killed = time.monotonic()
    a.server.wait(timeout=30)
    assert checkpointed(database, job) < TOTAL, "the job ended before A was killed"
    wait_until(lambda: at_b.get(job)["replica"] == "B", 2 * TAKEOVER_S, "B to take the job")
    took = time.monotonic() - killed
    done = at_b.wait(job, poll_s=0.2, timeout_s=300)
    replicas = {r["id"]: r for r in at_b.replicas()}
    # The same job, undisturbed, on B alone.
    again = at_b.submit(CORNELL, settings=SETTINGS, name="undisturbed")["id"]
    at_b.wait(again, poll_s=0.2, timeout_s=300)
    return job, took, done, replicas, again
