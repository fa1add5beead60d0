"""Multi-host: the compose topology without Docker (deploy/netns/farm.sh). PostgreSQL, the server
and two workers each on their own host (network namespace) on one LAN of veth links, configured
by environment variables only, render the Cornell box with the workers' traffic over TLS (the
server's gRPC port refuses plaintext); then one worker's link is cut in the middle of a job, and
the job still completes, with the same image. With two servers of one farm on hosts of their own,
one server is cut off from PostgreSQL alone while it renders a job: it stops leasing the job's
tasks, the other takes the job over and ends it, and once the route is back the first learns it
lost the job and overwrites nothing: the stored image is that of an undisturbed run.

Everything runs inside namespaces this test creates, on a private /24 that exists only there;
they are deleted at the end, also when the test fails."""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from renderfarm.client import Client
from renderfarm.infra.images import read_exr

from .conftest import CORNELL, ROOT
from .tools import require_tool
from .waiting import wait_until

FARM = ROOT / "deploy" / "netns" / "farm.sh"
SETTINGS = {
    "width": 128,
    "height": 128,
    "tile_size": 16,
    "max_spp": 128,
    "noise_threshold": 0,
    "seed": 11,
    "sampler": "sobol",
    "integrator": "path",
    "max_depth": 8,
}
TOTAL_SAMPLES = 128 * 128 * 128


@pytest.fixture(scope="module", autouse=True)
def _root_and_iproute2():
    require_tool(
        os.geteuid() == 0 and shutil.which("ip") is not None,
        "network namespaces need root and iproute2 (scripts/install-deps.sh --deploy-tools)",
    )


def _farm(*args: str, env: dict[str, str] | None = None, timeout: float = 180) -> str:
    done = subprocess.run(
        [str(FARM), *args],
        env={**os.environ, **(env or {})},
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    assert done.returncode == 0, f"farm.sh {args[0]} failed:\n{done.stdout}\n{done.stderr}"
    return done.stdout


def _state(state_dir: Path) -> dict[str, str]:
    pairs = (line.split("=", 1) for line in (state_dir / "netfarm.env").read_text().splitlines())
    return {k: v.strip('"') for k, v in pairs}


def _rgb_of(exr: bytes, tmp: Path, name: str) -> np.ndarray:
    path = tmp / name
    path.write_bytes(exr)
    channels = read_exr(str(path))
    return np.stack([channels["R"], channels["G"], channels["B"]], axis=-1)


def _workers(client: Client) -> dict[str, dict]:
    return {w["id"]: w for w in client.workers()}


@contextlib.contextmanager
def _running_farm(monkeypatch, **settings: str):
    """Start the hosts; always tear them down (namespaces, links, processes)."""
    _farm("sweep")  # leftovers of a test process that was killed before its clean-up
    state_dir = Path(tempfile.mkdtemp(prefix="netfarm-", dir="/tmp"))
    env = {
        "NETFARM_OWNER_PID": str(os.getpid()),
        "NETFARM_WORKERS": "2",
        "NETFARM_WORKER_THREADS": "1",
        "RENDERFARM_LEASE_S": "3",
        "RENDERFARM_HEARTBEAT_INTERVAL_S": "1",
        "RENDERFARM_CHECKPOINT_INTERVAL_S": "1",
        **settings,
    }
    try:
        _farm("up", str(state_dir), env=env)
        state = _state(state_dir)
        # The LAN is only reachable directly: never through a proxy from the environment.
        hosts = ",".join(u.split("//")[1].split(":")[0] for u in state["URLS"].split())
        monkeypatch.setenv("NO_PROXY", f"{state['SUBNET']}.0/24,{hosts}")
        monkeypatch.setenv("no_proxy", f"{state['SUBNET']}.0/24,{hosts}")
        yield state_dir, state
    finally:
        try:
            _farm("down", str(state_dir), timeout=120)
        finally:
            prefix = _state(state_dir).get("PREFIX", "") if state_dir.exists() else ""
            namespaces = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True)
            shutil.rmtree(state_dir, ignore_errors=True)
            assert not prefix or f"{prefix}-" not in namespaces.stdout, "namespaces left behind"


@pytest.fixture()
def netns_farm(monkeypatch):
    """PostgreSQL, the server and two workers."""
    with _running_farm(monkeypatch) as farm:
        yield farm


@pytest.fixture()
def two_server_farm(monkeypatch):
    """PostgreSQL, two servers of one farm and a worker serving both."""
    with _running_farm(
        monkeypatch,
        NETFARM_SERVERS="2",
        NETFARM_WORKERS="1",
        RENDERFARM_CHECKPOINT_INTERVAL_S="0.5",
    ) as farm:
        yield farm


@pytest.fixture(scope="module")
def standalone_rgb(worker_binary, tmp_path_factory) -> np.ndarray:
    out = tmp_path_factory.mktemp("standalone") / "alone.exr"
    subprocess.run(
        [
            worker_binary, "render", str(CORNELL), "-o", str(out),
            "--width", "128", "--height", "128", "--spp", "128", "--seed", "11",
            "--sampler", "sobol", "--integrator", "path", "--max-depth", "8", "--threads", "2",
        ],
        check=True,
        capture_output=True,
        timeout=300,
    )  # fmt: skip
    channels = read_exr(str(out))
    return np.stack([channels["R"], channels["G"], channels["B"]], axis=-1)


def _grpc_health(address: str, ca_file: str | None) -> int:
    """The gRPC health status of the server at address, over TLS checked against ca_file, or
    in plaintext when ca_file is None (the error code's name if the call fails)."""
    import grpc
    from grpc_health.v1 import health_pb2, health_pb2_grpc

    options = [("grpc.enable_http_proxy", 0)]
    if ca_file is None:
        channel = grpc.insecure_channel(address, options=options)
    else:
        credentials = grpc.ssl_channel_credentials(Path(ca_file).read_bytes())
        channel = grpc.secure_channel(address, credentials, options=options)
    with channel:
        try:
            return (
                health_pb2_grpc.HealthStub(channel)
                .Check(health_pb2.HealthCheckRequest(), timeout=10)
                .status
            )
        except grpc.RpcError as e:
            return e.code().name


def test_cut_worker_link_job_completes_with_the_same_image(netns_farm, standalone_rgb, tmp_path):
    from grpc_health.v1 import health_pb2

    state_dir, state = netns_farm
    # Worker traffic is TLS: the gRPC port answers with the farm's CA and never in plaintext.
    assert state["URL"].startswith("https://")
    assert _grpc_health(state["GRPC"], state["CA_FILE"]) == health_pb2.HealthCheckResponse.SERVING
    assert _grpc_health(state["GRPC"], None) in ("UNAVAILABLE", "DEADLINE_EXCEEDED")
    with Client(
        state["URL"], token=state["ADMIN_TOKEN"], timeout=30, ca_file=state["CA_FILE"]
    ) as client:
        assert client.ready()
        wait_until(lambda: len(client.workers()) == 2, 30, "both workers to connect")
        workers = _workers(client)
        assert set(workers) == {"worker1", "worker2"}

        # 1. Undisturbed: the four hosts render the Cornell box; the image equals a standalone
        #    render with the same settings and seed (to float32 rounding).
        job = client.submit(CORNELL, settings=SETTINGS, name="multihost undisturbed")
        job = client.wait(job["id"], poll_s=0.2, timeout_s=300)
        assert job["state"] == "completed", job["error"]
        assert job["progress"]["samples_merged"] == TOTAL_SAMPLES
        done = _workers(client)
        assert done["worker1"]["tasks_done"] > 0 and done["worker2"]["tasks_done"] > 0
        undisturbed = _rgb_of(client.image(job["id"], "exr"), tmp_path, "undisturbed.exr")
        np.testing.assert_allclose(undisturbed, standalone_rgb, rtol=8e-7, atol=1e-7)

        # 2. The same job again; once worker1 holds leased tasks, its link goes down.
        job = client.submit(CORNELL, settings=SETTINGS, name="multihost cut")
        before = done["worker1"]["tasks_done"]

        def worker1_busy():
            w = _workers(client).get("worker1")
            return w if w and w["tasks_done"] > before and w["tasks_in_flight"] > 0 else None

        wait_until(worker1_busy, 60, "worker1 to render part of the second job", poll_s=0.05)
        _farm("cut", str(state_dir), "worker1")
        cut_at = time.monotonic()
        # Counted after the cut: tasks worker1 finished while the cut was being made count as
        # before it; nothing may be added once its link is down.
        busy = _workers(client)["worker1"]
        running = client.get(job["id"])
        assert running["state"] == "running", "the job finished before the cut; make it longer"
        assert running["progress"]["samples_merged"] < TOTAL_SAMPLES

        # The server hears nothing more from worker1: its leases expire (RENDERFARM_LEASE_S=3)
        # and worker2 renders what worker1 held.
        job = client.wait(job["id"], poll_s=0.2, timeout_s=300)
        elapsed = time.monotonic() - cut_at
        assert job["state"] == "completed", job["error"]
        assert job["progress"]["samples_merged"] == TOTAL_SAMPLES
        after = _workers(client)
        if "worker1" in after:  # still listed until the server notices the dead stream
            # Results already on their way when the link went down (in the server's socket
            # buffers) may still be counted, at most one per task it held; a link still up
            # would have let worker1 render many more of the job's tasks.
            late = after["worker1"]["tasks_done"] - busy["tasks_done"]
            assert late <= busy["tasks_in_flight"], f"worker1 was not cut off ({late} more tasks)"
        assert after["worker2"]["tasks_done"] > done["worker2"]["tasks_done"]
        cut_rgb = _rgb_of(client.image(job["id"], "exr"), tmp_path, "cut.exr")

        # The database really is a host of its own: the server's connections reach it over
        # the LAN (TCP from the server's address to PostgreSQL's).
        sockets = subprocess.run(
            ["ip", "netns", "exec", f"{state['PREFIX']}-db", "ss", "-Htn", "state", "established"],
            capture_output=True, text=True, check=True, timeout=10,
        ).stdout  # fmt: skip
        assert f"{state['SUBNET']}.2:5432" in sockets and f"{state['SUBNET']}.3:" in sockets

    np.testing.assert_array_equal(cut_rgb, undisturbed)
    np.testing.assert_allclose(cut_rgb, standalone_rgb, rtol=8e-7, atol=1e-7)
    print(f"job with worker1 cut off completed {elapsed:.1f} s after the cut")


LONG = SETTINGS | {"max_spp": 1024}
LONG_SAMPLES = 128 * 128 * 1024


def _metric(url: str, state: dict[str, str], name: str) -> float:
    text = httpx.get(
        f"{url}/metrics",
        headers={"Authorization": f"Bearer {state['ADMIN_TOKEN']}"},
        verify=state["CA_FILE"],
        timeout=10,
    ).text
    return float(next(x.split()[1] for x in text.splitlines() if x.startswith(name + " ")))


def test_a_server_cut_off_from_the_database_stops_leasing_and_writing(two_server_farm, tmp_path):
    state_dir, state = two_server_farm
    url1, url2 = state["URLS"].split()
    assert url1 == state["URL"]
    kwargs = {"token": state["ADMIN_TOKEN"], "timeout": 30, "ca_file": state["CA_FILE"]}
    with Client(url1, **kwargs) as one, Client(url2, **kwargs) as two:
        wait_until(lambda: len(one.workers()) == len(two.workers()) == 1, 60, "the worker")
        assert {r["id"] for r in two.replicas()} == {"server", "server2"}
        reference = two.wait(two.submit(CORNELL, settings=LONG, name="undisturbed")["id"],
                             poll_s=0.2, timeout_s=600)  # fmt: skip
        assert reference["progress"]["samples_merged"] == LONG_SAMPLES
        undisturbed = _rgb_of(two.image(reference["id"], "exr"), tmp_path, "undisturbed.exr")

        job = one.submit(CORNELL, settings=LONG, name="cut off")["id"]
        wait_until(lambda: two.get(job)["replica"] == "server", 30, "server to hold the job")
        wait_until(
            lambda: two.get(job)["progress"]["samples_merged"] > LONG_SAMPLES // 10,
            120, "a checkpoint of a tenth",
        )  # fmt: skip
        _farm("cut-db", str(state_dir), "server")
        cut_at = time.monotonic()
        wait_until(lambda: two.get(job)["replica"] == "server2", 60, "server2 to take the job")
        took = time.monotonic() - cut_at
        # Cut off, `server` can no longer be sure it holds the job: it stopped leasing its
        # tasks before server2 could take it (its hold lapses a quarter lease early).
        assigned = _metric(url1, state, "renderfarm_tasks_assigned_total")
        at_takeover = two.get(job)["progress"]["samples_merged"]
        wait_until(
            lambda: two.get(job)["progress"]["samples_merged"] > at_takeover,
            120, "server2 to render the job",
        )  # fmt: skip
        assert _metric(url1, state, "renderfarm_tasks_assigned_total") == assigned
        done = two.wait(job, poll_s=0.2, timeout_s=600)
        # The route comes back: the server's stalled writes and renewals arrive, are refused
        # by the lease's epoch, and it drops the job.
        _farm("restore-db", str(state_dir), "server")
        wait_until(
            lambda: _metric(url1, state, "renderfarm_jobs_lost_total") >= 1,
            180, "server to learn that it lost the job", poll_s=0.5,
        )  # fmt: skip
        assert one.get(job)["replica"] == ""  # finished: nobody holds it
        stored = _rgb_of(one.image(job, "exr"), tmp_path, "cut-off.exr")
    assert done["state"] == "completed" and done["progress"]["samples_merged"] == LONG_SAMPLES
    assert took <= 15, f"server2 took the job {took:.1f} s after the cut"
    np.testing.assert_array_equal(stored, undisturbed)
    print(f"server2 took the job {took:.1f} s after server was cut off from the database")
