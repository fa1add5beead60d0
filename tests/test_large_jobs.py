"""Jobs against the server's memory settings, on a farm that has very little of it: a job whose
accumulators would outgrow RENDERFARM_MAX_JOB_MEMORY_MB is refused through REST and gRPC alike,
naming settings.width; one larger than RENDERFARM_TILE_CACHE_MB renders with its tiles in a
spill file, to the renderer's own image, and the file goes with the job."""

from __future__ import annotations

import subprocess

import numpy as np
import pytest

from renderfarm.cli.localfarm import LocalFarm
from renderfarm.infra.images import read_exr
from renderfarm.v1 import jobs_pb2

from .apihelpers import Apis, Error, cornell_glb
from .conftest import CORNELL
from .scrape import metric

LIMITS = {"RENDERFARM_MAX_JOB_MEMORY_MB": "8", "RENDERFARM_TILE_CACHE_MB": "1"}
# 200 x 120 at 16-pixel tiles: 1.7 MB of accumulators, 18 KB a tile, 104 tiles of which the
# 1 MB cache holds 56.
SPILLED = {"width": 200, "height": 120, "tile_size": 16, "max_spp": 32, "noise_threshold": 0}
SPILLED |= {"seed": 9}


@pytest.fixture(scope="module")
def small_farm(tmp_path_factory, worker_binary):
    data = tmp_path_factory.mktemp("small-farm")
    with LocalFarm(workers=2, data_dir=data, threads=1, env=LIMITS) as farm:
        apis = Apis(farm.url, farm.grpc_address)
        yield farm, apis, data
        apis.close()


def test_a_job_over_the_memory_limit_is_refused_through_both_apis(small_farm):
    _, apis, _ = small_farm
    big = {"width": 512, "height": 512, "max_spp": 1}  # 18 MB of accumulators
    answers = [
        apis.submit_rest(cornell_glb(), "cornell.glb", big, "too big"),
        apis.submit_rpc(cornell_glb(), "cornell.glb", big, "too big"),
    ]
    for answer in answers:
        assert isinstance(answer, Error), answer
        assert (answer.kind, answer.field) == ("invalid", "settings.width"), answer
        assert "512 x 512" in answer.message and "8 MB" in answer.message, answer.message
    # Tall rather than wide: still named by settings.width, the first of the two.
    tall = apis.submit_rest(cornell_glb(), "cornell.glb", {"width": 64, "height": 8192}, "tall")
    assert isinstance(tall, Error) and tall.field == "settings.width", tall
    assert not any(j["name"] in ("too big", "tall") for j in apis.client.list()["jobs"])


def test_a_job_larger_than_the_tile_cache_renders_from_its_spill_file(
    small_farm, worker_binary, tmp_path
):
    farm, apis, data = small_farm
    job = apis.submit_rest(cornell_glb(), "cornell.glb", SPILLED, "spilled")
    assert not isinstance(job, Error), job
    job = apis.client.wait(job["id"], poll_s=0.2, timeout_s=600)
    assert job["state"] == "completed"
    spill = data / "scratch" / f"{job['id']}.tiles"
    assert spill.exists(), "the job should have outgrown the 1 MB cache"
    assert metric(farm.url, "renderfarm_tile_spill_bytes") > 0
    assert metric(farm.url, "renderfarm_tile_memory_bytes") <= 2**20

    # Its image, read back from the file, is the renderer's own (as in tests/test_faults.py).
    alone = tmp_path / "alone.exr"
    args = [worker_binary, "render", str(CORNELL), "-o", str(alone), "--threads", "2"]
    args += ["--width", "200", "--height", "120", "--spp", "32", "--seed", "9"]
    subprocess.run(args, check=True, capture_output=True, timeout=600)
    farm_exr = tmp_path / "farm.exr"
    farm_exr.write_bytes(apis.client.image(job["id"], "exr"))
    got, want = read_exr(str(farm_exr)), read_exr(str(alone))
    for c in "RGB":
        np.testing.assert_allclose(got[c], want[c], rtol=1e-6, atol=1e-7)
    assert (got["spp"] == 32).all()

    # The same image through gRPC, and a preview at most 64 pixels on a side.
    exr_request = jobs_pb2.GetImageRequest(job_id=job["id"], format=jobs_pb2.IMAGE_FORMAT_EXR)
    rpc_exr = tmp_path / "rpc.exr"
    rpc_exr.write_bytes(apis.rpc("GetImage", exr_request).data)
    assert all(read_exr(str(rpc_exr))[c].tobytes() == got[c].tobytes() for c in got)
    for answer in (
        apis.rest("GET", f"/api/v1/jobs/{job['id']}/image.png", params={"max_size": 64}),
        apis.rpc("GetImage", jobs_pb2.GetImageRequest(job_id=job["id"], max_size=64)).data,
    ):
        assert answer[:8] == b"\x89PNG\r\n\x1a\n"
        width, height = int.from_bytes(answer[16:20], "big"), int.from_bytes(answer[20:24], "big")
        assert (width, height) == (50, 30)  # 200 x 120 by a factor of 4
    bad = apis.rest("GET", f"/api/v1/jobs/{job['id']}/image.png", params={"max_size": -1})
    assert isinstance(bad, Error) and (bad.kind, bad.field) == ("invalid", "max_size"), bad

    # An uncompressed EXR (faster to write) holds the same channels.
    plain = tmp_path / "plain.exr"
    plain.write_bytes(
        apis.rest("GET", f"/api/v1/jobs/{job['id']}/image.exr", params={"compression": "none"})
    )
    assert plain.stat().st_size > farm_exr.stat().st_size
    unpacked = read_exr(str(plain))
    assert all(unpacked[c].tobytes() == got[c].tobytes() for c in got)
    for bad in (
        apis.rest("GET", f"/api/v1/jobs/{job['id']}/image.exr", params={"compression": "lzma"}),
        apis.rpc("GetImage", jobs_pb2.GetImageRequest(
            job_id=job["id"], format=jobs_pb2.IMAGE_FORMAT_EXR, compression="lzma")),
    ):  # fmt: skip
        assert isinstance(bad, Error) and (bad.kind, bad.field) == ("invalid", "compression")

    # Deleting the job removes its file at once.
    assert apis.rest("DELETE", f"/api/v1/jobs/{job['id']}") is None
    assert not spill.exists()
    assert metric(farm.url, "renderfarm_tile_spill_bytes") == 0
