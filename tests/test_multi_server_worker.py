"""One C++ worker serves two farms at once (`renderfarm-worker connect --server A,B`, as it
serves the replicas of one farm): each farm sees it under its own id, both jobs complete, and
each image is the one a worker of that farm alone renders (the same bits: a task's result does
not depend on which server or how many the worker serves)."""

from __future__ import annotations

from pathlib import Path

from renderfarm.cli.localfarm import LocalFarm, spawn_workers, stop_processes
from renderfarm.client import Client
from renderfarm.infra.images import read_exr

from .apihelpers import TINY
from .conftest import CORNELL
from .waiting import wait_until

SETTINGS = {**TINY, "width": 32, "height": 32, "max_spp": 8, "seed": 5}


def _render(farm: LocalFarm, seed: int, out: Path) -> dict:
    with Client(farm.url) as client:
        job = client.submit(CORNELL, settings={**SETTINGS, "seed": seed}, name=f"seed-{seed}")
        done = client.wait(job["id"], timeout_s=180)
        assert done["state"] == "completed", done
        out.write_bytes(client.image(job["id"], "exr"))
        return {name: values.ravel().tolist() for name, values in read_exr(str(out)).items()}


def test_a_worker_serves_two_farms_with_the_images_each_renders_alone(tmp_path):
    a = LocalFarm(workers=0, data_dir=tmp_path / "a")
    b = LocalFarm(workers=0, data_dir=tmp_path / "b")
    with a, b:
        worker = spawn_workers(1, f"{a.grpc_address},{b.grpc_address}", threads=1,
                               log_dir=tmp_path)  # fmt: skip
        try:
            # Both farms see it, each under the worker's id followed by its own address.
            for farm in (a, b):
                with Client(farm.url) as client:
                    wait_until(lambda c=client: len(c.workers()) == 1, 60,
                               f"the worker to join {farm.grpc_address}")  # fmt: skip
                    (seen,) = client.workers()
                    assert seen["id"].endswith("@" + farm.grpc_address), seen
            both = (_render(a, 5, tmp_path / "a.exr"), _render(b, 6, tmp_path / "b.exr"))
        finally:
            stop_processes(worker)
        # Each farm again with a worker of its own: the same images, bit for bit.
        for farm in (a, b):
            farm.add_workers(1, threads=1)
        alone = (_render(a, 5, tmp_path / "a1.exr"), _render(b, 6, tmp_path / "b1.exr"))
    assert both == alone
    log = (tmp_path / "worker-0.log").read_text()
    assert f"connecting to {a.grpc_address}" in log and f"connecting to {b.grpc_address}" in log
