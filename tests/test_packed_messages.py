"""Packed messages (workers.proto: Hello.packed, Welcome.packed, Assigns, TileResults) against a
real server: a worker that reads packed assignments gets the leases of one change in one
message, and results sent several to a message are each merged exactly once, as if they had
come alone; a worker that is not packed never gets a packed message.

The fake workers here answer every task with known per-sample values (k / 8: exact in float32
at any sample count), so the image every pixel must converge to is known without the server:
the stored EXR must equal it exactly, whichever way the results travelled."""

from __future__ import annotations

import contextlib
import queue
import threading

import grpc
import numpy as np
import pytest

from renderfarm.cli.localfarm import LocalFarm
from renderfarm.client import Client
from renderfarm.infra.images import read_exr
from renderfarm.v1 import workers_pb2, workers_pb2_grpc

from .conftest import CORNELL

SIZE, TILE = 64, 16
SETTINGS = {"width": SIZE, "height": SIZE, "tile_size": TILE, "max_spp": 24, "seed": 1,
            "noise_threshold": 0}  # fmt: skip


def sample_value(x: np.ndarray, y: np.ndarray, channel: int) -> np.ndarray:
    """Every sample's radiance at pixel (x, y): a multiple of 1/8, so sums stay exact."""
    return ((x + 2 * y + 3 * channel) % 7 + 1) / 8.0


def expected_image() -> np.ndarray:
    y, x = np.mgrid[0:SIZE, 0:SIZE]
    return np.stack([sample_value(x, y, c) for c in range(3)], axis=-1)


def tile_result(task, corrupt: bool = False) -> workers_pb2.TileResult:
    r = task.rect
    y, x = np.mgrid[r.y0 : r.y0 + r.height, r.x0 : r.x0 + r.width]
    rgb = np.stack([sample_value(x, y, c) for c in range(3)], axis=-1) * task.sample_count
    raw = rgb.astype("<f4").tobytes()
    return workers_pb2.TileResult(
        task_id=task.task_id,
        job_id=task.job_id,
        tile_index=task.tile_index,
        batch_index=task.batch_index,
        # A result for other samples than its task's: refused (a mismatch), leased again.
        sample_start=task.sample_start + (1 if corrupt else 0),
        sample_count=task.sample_count,
        rect=r,
        rgb_sum=raw,
        luminance_m2=np.zeros(r.width * r.height, "<f4").tobytes(),
        coverage_sum=np.full(r.width * r.height, task.sample_count, "<f4").tobytes(),
        render_seconds=0.001,
    )


class FakeWorker(threading.Thread):
    """A worker stream answering each message's tasks at once: in one TileResults message when
    packed (the first one with a refused result among good ones), else one message each. Every
    server message kind is logged as (kind, task count); stop() ends the stream."""

    def __init__(self, address: str, name: str, packed: bool):
        super().__init__(daemon=True)
        self.address, self.name, self.packed = address, name, packed
        self.log: list[tuple[str, int]] = []
        self.outbox: queue.Queue = queue.Queue()
        self.call = None
        self.stopped = threading.Event()

    def stop(self) -> None:
        self.stopped.set()
        self.outbox.put(None)
        if self.call is not None:
            self.call.cancel()

    def _requests(self):
        while True:
            msg = self.outbox.get()
            if msg is None:
                return
            yield msg

    def run(self) -> None:
        hello = workers_pb2.Hello(worker_id=self.name, hostname="test", cores=8, max_in_flight=8)
        hello.packed = self.packed
        self.outbox.put(workers_pb2.WorkerMessage(hello=hello))
        corrupt_once = self.packed
        with grpc.insecure_channel(self.address) as channel:
            stub = workers_pb2_grpc.WorkerServiceStub(channel)
            self.call = stub.Connect(self._requests(), timeout=180)
            if self.stopped.is_set():
                self.call.cancel()
            with contextlib.suppress(grpc.RpcError):  # cancelled by stop()
                for msg in self.call:
                    kind = msg.WhichOneof("msg")
                    if kind == "welcome":
                        self.log.append(("welcome", int(msg.welcome.packed)))
                        continue
                    tasks = [msg.assign.task] if kind == "assign" else []
                    if kind == "assigns":
                        tasks = [a.task for a in msg.assigns.assigns]
                    self.log.append((kind, len(tasks)))
                    if len(tasks) > 1 and self.packed:
                        results = [tile_result(t) for t in tasks]
                        if corrupt_once:
                            results[0] = tile_result(tasks[0], corrupt=True)
                            corrupt_once = False
                        self.outbox.put(workers_pb2.WorkerMessage(
                            results=workers_pb2.TileResults(results=results)))  # fmt: skip
                    else:
                        for t in tasks:
                            self.outbox.put(workers_pb2.WorkerMessage(result=tile_result(t)))


@pytest.fixture(scope="module")
def farm(tmp_path_factory):
    with LocalFarm(workers=0, data_dir=tmp_path_factory.mktemp("packed")) as running:
        yield running


@pytest.mark.parametrize("packed", [True, False])
def test_results_packed_or_not_are_each_merged_once(farm, packed, tmp_path):
    with Client(farm.url) as client:
        job = client.submit(CORNELL, settings=SETTINGS, name=f"packed={packed}")
        worker = FakeWorker(farm.grpc_address, f"fake-{packed}", packed)
        worker.start()
        try:
            done = client.wait(job["id"], poll_s=0.1, timeout_s=120)
        finally:
            worker.stop()
            worker.join(timeout=30)
        assert done["state"] == "completed", done
        exr = tmp_path / "image.exr"
        exr.write_bytes(client.image(job["id"], "exr"))
    channels = read_exr(str(exr))
    rgb = np.stack([channels["R"], channels["G"], channels["B"]], axis=-1)
    np.testing.assert_array_equal(rgb, expected_image().astype(np.float32))
    np.testing.assert_array_equal(channels["spp"], SETTINGS["max_spp"])
    log = worker.log
    assert log[0] == ("welcome", 1)  # the server reads packed results
    kinds = {kind for kind, _ in log[1:]}
    if packed:
        # The first leases (the worker's whole credit) came in one message.
        assert log[1][0] == "assigns" and log[1][1] > 1, log[:5]
    else:
        assert "assigns" not in kinds, log[:20]
