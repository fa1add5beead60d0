"""Operator control of workers on a real farm (embedded PostgreSQL, server, two real workers):
drain finishes the tasks in hand then takes none; disable hands them back and the other worker
renders the same image as an undisturbed job; admins only; the CLI commands."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from renderfarm.cli.localfarm import LocalFarm
from renderfarm.client import ApiError, Client
from renderfarm.infra.images import read_exr

from .apihelpers import create_token
from .conftest import CORNELL
from .waiting import wait_until

CLI = [sys.executable, "-m", "renderfarm"]
# Enough tasks (36 tiles, several batches each) that a worker holds some when it is drained.
JOB = {"width": 96, "height": 96, "tile_size": 16, "seed": 11, "noise_threshold": 0, "max_spp": 64}


def _token(data_dir: Path, name: str, admin: bool) -> str:
    return create_token(data_dir, name, admin)["token"]


@pytest.fixture(scope="module")
def farm(tmp_path_factory):
    data = tmp_path_factory.mktemp("pools")
    tokens = {"root": _token(data, "root", True), "alice": _token(data, "alice", False)}
    with LocalFarm(workers=2, data_dir=data, threads=1) as f:
        f.tokens = tokens
        with Client(f.url, token=tokens["root"]) as c:
            wait_until(lambda: len(c.workers()) == 2, 30, "two workers")
        yield f


@pytest.fixture()
def admin(farm):
    with Client(farm.url, token=farm.tokens["root"], timeout=60) as c:
        yield c
        for w in c.workers():  # every test starts with both workers active
            if w["state"] != "active":
                c.enable_worker(w["id"])


def _worker(client: Client, worker_id: str) -> dict:
    return next(w for w in client.workers() if w["id"] == worker_id)


def _busy_worker(client: Client) -> dict:
    """A worker holding tasks of the running job (polled until one does)."""
    return wait_until(
        lambda: next((w for w in client.workers() if w["tasks_in_flight"] > 0), None),
        60,
        "a worker holding tasks",
    )


def _channels(client: Client, job_id: str, tmp_path: Path) -> dict[str, np.ndarray]:
    path = tmp_path / f"{job_id}.exr"
    path.write_bytes(client.image(job_id, "exr"))
    return read_exr(str(path))


def test_only_admin_tokens_control_workers(farm, admin):
    worker_id = admin.workers()[0]["id"]
    with Client(farm.url, token=farm.tokens["alice"]) as alice:
        assert alice.workers()  # anyone may list them
        for act in (alice.drain_worker, alice.disable_worker, alice.enable_worker):
            with pytest.raises(ApiError) as e:
                act(worker_id)
            assert e.value.status == 403
            assert "admin" in e.value.message
    assert _worker(admin, worker_id)["state"] == "active"
    with pytest.raises(ApiError) as e:
        admin.drain_worker("no-such-worker")
    assert e.value.status == 404


def test_a_drained_worker_finishes_its_tasks_then_takes_none(admin):
    job = admin.submit(CORNELL, settings=JOB, name="drain")
    busy = _busy_worker(admin)
    assert admin.drain_worker(busy["id"])["state"] in ("draining", "drained")
    drained = wait_until(
        lambda: (w := _worker(admin, busy["id"]))["state"] == "drained" and w,
        60,
        "the worker drained",
    )
    assert drained["tasks_in_flight"] == 0
    # Its tasks were finished by it, not handed back: it sent results after the drain.
    assert drained["tasks_done"] >= busy["tasks_done"]
    done = admin.wait(job["id"], poll_s=0.1, timeout_s=300)
    assert done["state"] == "completed"
    after = _worker(admin, busy["id"])
    assert after["tasks_done"] == drained["tasks_done"]  # took nothing more
    assert after["state"] == "drained"
    assert admin.enable_worker(busy["id"])["state"] == "active"


def test_a_disabled_workers_tasks_go_to_another_worker_with_the_same_image(admin, tmp_path):
    reference = admin.wait(
        admin.submit(CORNELL, settings=JOB, name="undisturbed")["id"], poll_s=0.1, timeout_s=300
    )
    assert reference["state"] == "completed"
    job = admin.submit(CORNELL, settings=JOB, name="disabled midway")
    busy = _busy_worker(admin)
    disabled = admin.disable_worker(busy["id"])
    assert disabled["state"] == "disabled"
    assert disabled["tasks_in_flight"] == 0  # handed back at once
    done = admin.wait(job["id"], poll_s=0.1, timeout_s=300)
    assert done["state"] == "completed"
    assert _worker(admin, busy["id"])["tasks_in_flight"] == 0
    a, b = _channels(admin, reference["id"], tmp_path), _channels(admin, job["id"], tmp_path)
    assert sorted(a) == sorted(b)
    for name in a:
        assert np.array_equal(a[name], b[name]), f"channel {name} differs"


def test_cli_drains_disables_and_enables(farm, admin):
    env = {**os.environ, "RENDERFARM_URL": farm.url, "RENDERFARM_TOKEN": farm.tokens["root"]}

    def cli(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run(CLI + list(args), capture_output=True, text=True, timeout=60, env=env)

    worker_id = admin.workers()[0]["id"]
    for action, state in (("drain", "drained"), ("disable", "disabled"), ("enable", "active")):
        done = cli("workers", action, worker_id)
        assert done.returncode == 0, done.stderr
        assert done.stdout.split() == [worker_id, state]
    listed = cli("workers", "--json")
    assert listed.returncode == 0, listed.stderr
    assert {w["id"]: w["state"] for w in json.loads(listed.stdout)}[worker_id] == "active"
    table = cli("workers")
    assert "STATE" in table.stdout and "FAILED" in table.stdout
    missing = cli("workers", "drain")
    assert missing.returncode == 2 and "worker ID" in missing.stderr
    refused = subprocess.run(
        CLI + ["workers", "disable", worker_id], capture_output=True, text=True, timeout=60,
        env={**env, "RENDERFARM_TOKEN": farm.tokens["alice"]},
    )  # fmt: skip
    assert refused.returncode != 0 and "admin" in refused.stderr


def test_grpc_set_worker_mode_is_for_admins(farm, admin):
    import grpc

    from renderfarm.v1 import jobs_pb2, jobs_pb2_grpc

    worker_id = admin.workers()[0]["id"]
    with grpc.insecure_channel(farm.grpc_address) as channel:
        stub = jobs_pb2_grpc.JobServiceStub(channel)
        request = jobs_pb2.SetWorkerModeRequest(
            worker_id=worker_id, mode=jobs_pb2.WORKER_MODE_DRAINING
        )
        with pytest.raises(grpc.RpcError) as e:
            stub.SetWorkerMode(
                request, metadata=[("authorization", f"Bearer {farm.tokens['alice']}")], timeout=30
            )
        assert e.value.code() == grpc.StatusCode.PERMISSION_DENIED
        root = [("authorization", f"Bearer {farm.tokens['root']}")]
        answer = stub.SetWorkerMode(request, metadata=root, timeout=30)
        assert answer.worker.id == worker_id and answer.worker.state in ("draining", "drained")
        listed = stub.ListWorkers(jobs_pb2.ListWorkersRequest(), metadata=root, timeout=30)
        assert {w.id: w.state for w in listed.workers}[worker_id] == answer.worker.state
        enable = jobs_pb2.SetWorkerModeRequest(
            worker_id=worker_id, mode=jobs_pb2.WORKER_MODE_ACTIVE
        )
        assert stub.SetWorkerMode(enable, metadata=root, timeout=30).worker.state == "active"


def test_bad_tags_are_refused_naming_the_field(admin, worker_binary):
    for bad in (["Big-Mem"], ["gpu!less"], ["gpu less"], ["x" * 65], ["-lead"]):
        with pytest.raises(ApiError) as e:
            admin.submit(CORNELL, settings=JOB, require_tags=bad)
        assert e.value.status == 400 and e.value.field == "require_tags", bad
    done = subprocess.run(
        [worker_binary, "connect", "--server", "127.0.0.1:1", "--tag", "Bad!"],
        capture_output=True, text=True, timeout=30,
    )  # fmt: skip
    assert done.returncode == 2 and "--tag 'Bad!'" in done.stderr


def test_tags_route_a_job_to_the_workers_having_them(farm, admin):
    """Last in the module: it adds a tagged worker to the farm."""
    job = admin.submit(CORNELL, settings=JOB, name="tagged", require_tags=["gpu-less", "big-mem"])
    assert job["require_tags"] == ["big-mem", "gpu-less"]
    waiting = wait_until(
        lambda: (j := admin.get(job["id"]))["error"] and j, 30, "the job to say why it waits"
    )
    assert waiting["state"] == "queued"
    assert waiting["error"] == "waiting for a worker with the tags big-mem, gpu-less"
    before = {w["id"]: w["tasks_done"] for w in admin.workers()}
    farm.add_workers(1, tags=["big-mem", "gpu-less", "spare"])
    tagged = wait_until(
        lambda: next((w for w in admin.workers() if w["id"] not in before), None),
        60,
        "the tagged worker",
    )
    assert tagged["tags"] == ["big-mem", "gpu-less", "spare"]
    done = admin.wait(job["id"], poll_s=0.1, timeout_s=300)
    assert done["state"] == "completed" and done["error"] == ""
    after = {w["id"]: w["tasks_done"] for w in admin.workers()}
    assert {i: after[i] for i in before} == before  # the untagged workers rendered none of it
    assert after[tagged["id"]] > 0
