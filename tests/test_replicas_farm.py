"""Two `renderfarm server` processes over one PostgreSQL form one farm (#39): a job submitted to
server A, which A renders with its worker, moves to server B when A is killed with SIGKILL, within
the bound docs/architecture.md gives ("Ownership, leases and fencing": the job lease, 8 s, and
a quarter of it), resumes from A's last checkpoint, and ends with the tiles of an undisturbed
run of the same job, bit for bit. One worker serves both servers (`renderfarm-worker connect
--server A,B`), as a farm's workers serve its replicas: it renders the job for A, then for B."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time

import httpx
import psycopg
import pytest

from renderfarm.cli.localfarm import LocalFarm, spawn_workers, stop_processes
from renderfarm.client import ApiError, Client
from renderfarm.infra.embedded_db import EmbeddedPostgres

from .conftest import CORNELL
from .scrape import metric
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


def epochs(url: str, job_ids: list[str]) -> list[int]:
    """The lease epoch of each job: 1 while one server has held it, +1 per move."""
    with psycopg.connect(url) as conn:
        rows = dict(conn.execute("SELECT job_id, epoch FROM job_leases").fetchall())
    return [rows[j] for j in job_ids]


def test_kill_9_of_one_of_two_servers_moves_its_job_to_the_other(tmp_path, database):
    env = {"RENDERFARM_DATABASE_URL": database, **FAST}
    a = LocalFarm(workers=0, data_dir=tmp_path / "a", env={**env, "RENDERFARM_REPLICA_ID": "A"})
    b = LocalFarm(workers=0, data_dir=tmp_path / "b", env={**env, "RENDERFARM_REPLICA_ID": "B"})
    with a, b, Client(a.url) as at_a, Client(b.url) as at_b:
        worker = spawn_workers(1, f"{a.grpc_address},{b.grpc_address}", threads=1,
                               log_dir=tmp_path)  # fmt: skip
        try:
            moved, took, done, replicas, again, poller = _kill_a_mid_job(database, a, at_a, at_b)
        finally:
            stop_processes(worker)
    # Meanwhile B, the survivor, answered every request about the job and the job list (2xx,
    # or a 503/429 with Retry-After that the client followed).
    assert poller.failures == [], poller.failures[:5]
    assert poller.answers > 10
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
    poller = Poller([at_b.url], [job])
    poller.thread.start()
    try:
        a.server.send_signal(signal.SIGKILL)
        killed = time.monotonic()
        a.server.wait(timeout=30)
        assert checkpointed(database, job) < TOTAL, "the job ended before A was killed"
        wait_until(lambda: at_b.get(job)["replica"] == "B", 2 * TAKEOVER_S, "B to take the job")
        took = time.monotonic() - killed
        done = at_b.wait(job, poll_s=0.2, timeout_s=300)
    finally:
        poller.stop.set()
        poller.thread.join(timeout=60)
    replicas = {r["id"]: r for r in at_b.replicas()}
    # The same job, undisturbed, on B alone.
    again = at_b.submit(CORNELL, settings=SETTINGS, name="undisturbed")["id"]
    at_b.wait(again, poll_s=0.2, timeout_s=300)
    return job, took, done, replicas, again, poller


# Long enough to be mid-render through a server joining or a rolling restart on a busy machine
# (about 15 s of one render thread each here), short enough for CI.
LONG = SETTINGS | {"width": 96, "height": 96, "max_spp": 2048}
LONG_TOTAL = 96 * 96 * 2048
# A rolling restart takes two server starts and drains: twice as long (about 30 s each here).
ROLLING = LONG | {"max_spp": 4096}
ROLLING_TOTAL = 2 * LONG_TOTAL


def test_a_server_that_joins_takes_its_share_of_the_jobs_with_their_bits(tmp_path, database):
    """Two jobs rendering on A; B starts: A hands the newer one over (checkpointed, released)
    and B takes it, mid-render, while A keeps the older. Both end with the same tiles (same
    scene, settings and seed): the moved job's bits are those of the one never moved."""
    env = {"RENDERFARM_DATABASE_URL": database, **FAST}
    a = LocalFarm(workers=0, data_dir=tmp_path / "a", env={**env, "RENDERFARM_REPLICA_ID": "A"})
    b = LocalFarm(workers=0, data_dir=tmp_path / "b", env={**env, "RENDERFARM_REPLICA_ID": "B"})
    workers = []
    try:
        with a, Client(a.url) as at_a:
            workers += spawn_workers(1, a.grpc_address, threads=1, log_dir=tmp_path)
            jobs = [at_a.submit(CORNELL, settings=LONG, name=f"job {i}")["id"] for i in (0, 1)]
            wait_until(
                lambda: all(checkpointed(database, j) > 0 for j in jobs), 300, "two checkpoints"
            )
            with b, Client(b.url) as at_b:
                workers += spawn_workers(
                    1, b.grpc_address, threads=1, log_dir=tmp_path, first_index=1
                )
                wait_until(lambda: at_b.get(jobs[1])["replica"] == "B", 60, "B to take job 1")
                moved_at = checkpointed(database, jobs[1])
                assert at_b.get(jobs[0])["replica"] == "A"
                done = [at_b.wait(j, poll_s=0.2, timeout_s=600) for j in jobs]
                listing = subprocess.run(
                    [sys.executable, "-m", "renderfarm", "replicas", "--url", b.url],
                    capture_output=True, text=True, timeout=60,
                )  # fmt: skip
                handed, lost = (
                    metric(a.url, "renderfarm_jobs_handed_off_total"),
                    metric(a.url, "renderfarm_jobs_lost_total"),
                )
    finally:
        stop_processes(workers)
    assert 0 < moved_at < LONG_TOTAL, "job 1 moved mid-render"
    assert [d["state"] for d in done] == ["completed"] * 2
    assert [d["progress"]["samples_merged"] for d in done] == [LONG_TOTAL] * 2
    assert epochs(database, jobs) == [1, 2], "each job moved at most once: no ping-pong"
    assert (handed, lost) == (1, 0)
    assert tiles(database, jobs[0]) == tiles(database, jobs[1])
    # The CLI lists both servers, live.
    rows = [line.split() for line in listing.stdout.splitlines()[1:]]
    assert listing.returncode == 0 and [r[:2] for r in rows] == [["A", "yes"], ["B", "yes"]]


class Poller:
    """A client of the farm behind a load balancer: asks the servers in `rotation` (the
    balancer's healthy set, which a server leaves before it is stopped) for the jobs and the
    job list in turn, following Retry-After (the client does); every failure is kept."""

    def __init__(self, urls: list[str], job_ids: list[str]):
        self.rotation = list(urls)
        self.job_ids = job_ids
        self.lock = threading.Lock()
        self.failures: list[str] = []
        self.answers = 0
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        clients: dict[str, Client] = {}
        turn = 0
        while not self.stop.is_set():
            with self.lock:  # a server leaves the rotation between two rounds, never in one
                url = self.rotation[turn % len(self.rotation)]
                turn += 1
                client = clients.setdefault(url, Client(url, timeout=30))
                try:
                    for job_id in self.job_ids:
                        client.get(job_id)
                    client.list()
                    self.answers += 1
                except (ApiError, httpx.HTTPError) as e:
                    self.failures.append(f"{url}: {e!r}")
            self.stop.wait(0.05)
        for client in clients.values():
            client.close()

    def leave(self, url: str) -> None:
        """Once the round in progress (which may be asking `url`) has ended."""
        with self.lock:
            self.rotation.remove(url)

    def join(self, url: str) -> None:
        with self.lock:
            self.rotation.append(url)


def test_a_rolling_restart_of_every_server_fails_no_request_and_keeps_the_bits(tmp_path, database):
    """Two servers, two jobs (shared between them), one worker serving both. Each server in
    turn leaves the balancer, is stopped with SIGTERM (it checkpoints and hands its jobs over)
    and started again. No request of a client polling the farm meanwhile fails, the jobs
    complete with every sample merged once, and their tiles are those of an undisturbed run."""
    env = {"RENDERFARM_DATABASE_URL": database, **FAST}
    a = LocalFarm(workers=0, data_dir=tmp_path / "a", env={**env, "RENDERFARM_REPLICA_ID": "A"})
    b = LocalFarm(workers=0, data_dir=tmp_path / "b", env={**env, "RENDERFARM_REPLICA_ID": "B"})
    with a, b, Client(a.url) as at_a:
        worker = spawn_workers(1, f"{a.grpc_address},{b.grpc_address}", threads=1,
                               log_dir=tmp_path)  # fmt: skip
        try:
            jobs = [at_a.submit(CORNELL, settings=ROLLING, name=f"job {i}")["id"] for i in (0, 1)]
            wait_until(lambda: {at_a.get(j)["replica"] for j in jobs} == {"A", "B"}, 60, "a share")
            poller = Poller([a.url, b.url], jobs)
            poller.thread.start()
            try:
                for farm in (a, b):
                    before = [checkpointed(database, j) for j in jobs]
                    wait_until(
                        lambda b=before: all(checkpointed(database, j) > n for j, n in
                                             zip(jobs, b, strict=True)),
                        120, "both jobs to progress",
                    )  # fmt: skip
                    poller.leave(farm.url)
                    farm.server.send_signal(signal.SIGTERM)
                    assert farm.server.wait(timeout=60) == 0
                    now = [checkpointed(database, j) for j in jobs]
                    assert max(now) < ROLLING_TOTAL, f"a job ended before the restart: {now}"
                    farm.start_server()
                    poller.join(farm.url)
                done = [at_a.wait(j, poll_s=0.2, timeout_s=600) for j in jobs]
            finally:
                poller.stop.set()
                poller.thread.join(timeout=60)
            again = at_a.submit(CORNELL, settings=ROLLING, name="undisturbed")["id"]
            at_a.wait(again, poll_s=0.2, timeout_s=600)
        finally:
            stop_processes(worker)
    assert poller.failures == [], poller.failures[:5]
    assert poller.answers > 20
    assert [d["state"] for d in done] == ["completed"] * 2
    assert [d["progress"]["samples_merged"] for d in done] == [ROLLING_TOTAL] * 2
    assert tiles(database, jobs[0]) == tiles(database, again)
    assert tiles(database, jobs[1]) == tiles(database, again)
