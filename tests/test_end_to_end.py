"""End to end: the Cornell box through REST on a local farm with 2 real workers."""

from __future__ import annotations

import subprocess

import grpc
import numpy as np
import pytest

from renderfarm.client import ApiError
from renderfarm.infra.images import read_exr
from renderfarm.v1 import jobs_pb2, jobs_pb2_grpc

from .conftest import CORNELL
from .waiting import wait_until

SETTINGS = {
    "width": 64,
    "height": 64,
    "tile_size": 16,
    "max_spp": 16,
    "noise_threshold": 0,
    "seed": 7,
    "sampler": "sobol",
    "integrator": "path",
    "max_depth": 8,
}


def _rgb(path) -> np.ndarray:
    channels = read_exr(str(path))
    return np.stack([channels["R"], channels["G"], channels["B"]], axis=-1)


def _wait_for_workers(client, count: int, timeout_s: float = 30) -> None:
    wait_until(lambda: len(client.workers()) >= count, timeout_s, f"{count} workers connected")


@pytest.fixture(scope="module")
def cornell_job(farm, tmp_path_factory):
    """Render the Cornell box on the farm once; return (job, path of its EXR)."""
    from renderfarm.client import Client

    with Client(farm.url, timeout=60) as client:
        _wait_for_workers(client, 2)
        job = client.submit(CORNELL, settings=SETTINGS, name="cornell e2e")
        assert job["state"] in ("queued", "running")
        job = client.wait(job["id"], poll_s=0.2, timeout_s=600)
        out = tmp_path_factory.mktemp("e2e") / "farm.exr"
        out.write_bytes(client.image(job["id"], "exr"))
        png = client.image(job["id"], "png")
        assert png[:8] == b"\x89PNG\r\n\x1a\n"
    return job, out


def test_job_completes_with_every_sample(cornell_job):
    job, _ = cornell_job
    assert job["state"] == "completed", job["error"]
    p = job["progress"]
    assert p["tiles_done"] == p["tiles_total"] == p["tiles_previewed"] == 16
    assert p["mean_spp"] == 16
    assert p["samples_merged"] == 64 * 64 * 16


def test_image_looks_like_a_cornell_box(cornell_job):
    _, exr = cornell_job
    channels = read_exr(str(exr))
    rgb = _rgb(exr)
    assert np.isfinite(rgb).all() and (rgb >= 0).all()
    assert (channels["spp"] == 16).all()
    h, w, _ = rgb.shape
    mid = slice(int(0.4 * h), int(0.6 * h))
    left = rgb[mid, int(0.04 * w) : int(0.12 * w)].reshape(-1, 3).mean(axis=0)
    right = rgb[mid, int(0.88 * w) : int(0.96 * w)].reshape(-1, 3).mean(axis=0)
    assert left[0] > 2 * left[1] and left[0] > 2 * left[2], f"left wall not red: {left}"
    assert right[1] > 1.5 * right[0] and right[1] > 1.5 * right[2], f"right wall not green: {right}"
    luminance = rgb @ np.array([0.2126, 0.7152, 0.0722])
    top_centre = luminance[: int(0.25 * h), int(0.35 * w) : int(0.65 * w)]
    walls = max(left @ [0.2126, 0.7152, 0.0722], right @ [0.2126, 0.7152, 0.0722])
    assert top_centre.max() > 5 * walls, "the ceiling light should outshine the walls"


def test_farm_image_equals_standalone_render(cornell_job, worker_binary, tmp_path):
    """The image is a pure function of scene, settings and seed (docs/architecture.md,
    "Determinism"), so the farm (2 workers, tiles and batches in any order) equals one
    standalone render."""
    _, farm_exr = cornell_job
    alone = tmp_path / "alone.exr"
    subprocess.run(
        [
            worker_binary, "render", str(CORNELL), "-o", str(alone),
            "--width", "64", "--height", "64", "--spp", "16", "--seed", "7",
            "--sampler", "sobol", "--integrator", "path", "--max-depth", "8", "--threads", "2",
        ],
        check=True,
        capture_output=True,
        timeout=300,
    )  # fmt: skip
    a, b = _rgb(farm_exr), _rgb(alone)
    assert a.shape == b.shape
    np.testing.assert_allclose(a, b, rtol=2e-7 * 4, atol=1e-7)
    # The alpha (share of samples whose camera ray hit geometry) is a count over the same
    # samples: equal exactly, and within [0, 1].
    farm_alpha, alone_alpha = read_exr(str(farm_exr))["A"], read_exr(str(alone))["A"]
    np.testing.assert_array_equal(farm_alpha, alone_alpha)
    assert 0 <= farm_alpha.min() and farm_alpha.max() <= 1


def test_grpc_job_service_sees_the_same_state(farm, cornell_job):
    job, _ = cornell_job
    with grpc.insecure_channel(farm.grpc_address) as channel:
        stub = jobs_pb2_grpc.JobServiceStub(channel)
        got = stub.GetJob(jobs_pb2.GetJobRequest(job_id=job["id"]), timeout=10).job
        assert got.state == jobs_pb2.JOB_STATE_COMPLETED
        assert got.progress.samples_merged == job["progress"]["samples_merged"]
        assert got.settings.max_spp == 16 and got.settings.seed == 7
        listed = stub.ListJobs(jobs_pb2.ListJobsRequest(page_size=500), timeout=10).jobs
        assert job["id"] in [j.id for j in listed]
        with pytest.raises(grpc.RpcError) as err:
            stub.SubmitJob(
                jobs_pb2.SubmitJobRequest(
                    scene_data=b"not a scene", settings=jobs_pb2.RenderSettings(max_spp=4)
                ),
                timeout=10,
            )
        assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert "glTF" in err.value.details()


@pytest.mark.parametrize(
    "files,settings,status,needle",
    [
        ({"scene": ("notes.txt", b"hello, not a scene", "text/plain")}, {}, 400, "not a glTF"),
        ({}, {}, 400, "scene is required"),
        (None, {"max_spp": -4}, 400, "settings.max_spp"),
        (None, {"spp": -1}, 400, "settings.spp"),
        (None, {"exposure": 2}, 400, "unknown setting 'exposure'"),
        (None, {"width": 10**9}, 400, "settings.width"),
        (None, {"sampler": "magic"}, 400, "settings.sampler"),
    ],
)
def test_bad_input_gets_a_clear_4xx(client, files, settings, status, needle):
    import json

    if files is None:
        files = {"scene": ("cornell.glb", _glb(), "model/gltf-binary")}
    # Always multipart, like a browser form: the settings travel as a JSON text field.
    parts = {**files, "settings": (None, json.dumps(settings))}
    r = client.http.post("/api/v1/jobs", files=parts)
    assert r.status_code == status, r.text
    assert needle in r.json()["detail"]


def test_unknown_job_and_stored_scene_are_404(client):
    with pytest.raises(ApiError) as err:
        client.get("nosuchjob")
    assert err.value.status == 404
    with pytest.raises(ApiError) as err:
        client.submit(scene_sha256="0" * 64, settings={"max_spp": 1})
    assert err.value.status == 404 and "no stored scene" in err.value.message


def _glb() -> bytes:
    from renderfarm.domain.scenes.pack import pack_gltf

    return pack_gltf(CORNELL)


def test_stop_records_and_convergence_history(client, cornell_job):
    job, _ = cornell_job
    got = client.get(job["id"])
    stops = got["stops"]
    assert sorted(s["tile"] for s in stops) == list(range(16))
    assert all(s["reason"] == "max_spp" and s["spp"] == 16 for s in stops)
    points = client.http.get(f"/api/v1/jobs/{job['id']}/convergence").json()
    assert points and points[-1]["mean_spp"] == 16
    times = [p["t"] for p in points]
    assert times == sorted(times)


def _tiny_hdr(path) -> bytes:
    import OpenImageIO as oiio

    spec = oiio.ImageSpec(8, 4, 3, oiio.FLOAT)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec)
    out.write_image(np.full((4, 8, 3), 0.5, dtype=np.float32))
    out.close()
    return path.read_bytes()


def test_environment_map_is_stored_and_referenced_by_hash(client, tmp_path):
    import hashlib
    import json

    hdr = _tiny_hdr(tmp_path / "sky.hdr")
    parts = {
        "scene": ("cornell.glb", _glb(), "model/gltf-binary"),
        "environment": ("sky.hdr", hdr, "application/octet-stream"),
        "settings": (None, json.dumps({"max_spp": 1, "width": 16, "height": 16})),
    }
    r = client.http.post("/api/v1/jobs", files=parts)
    assert r.status_code == 201, r.text
    job = r.json()
    assert job["settings"]["environment"] == hashlib.sha256(hdr).hexdigest()
    client.cancel(job["id"])
    # The stored map can be named by hash alone; an unknown hash is a 404.
    again = client.submit(
        scene_sha256=job["scene_sha256"],
        settings={"environment": job["settings"]["environment"], "max_spp": 1, "width": 16},
    )
    assert again["settings"]["environment"] == job["settings"]["environment"]
    client.cancel(again["id"])
    with pytest.raises(ApiError) as err:
        client.submit(scene_sha256=job["scene_sha256"], settings={"environment": "ab" * 32})
    assert err.value.status == 404 and "environment" in err.value.message
    # An environment map is stored beside scenes but cannot be rendered as one.
    with pytest.raises(ApiError) as err:
        client.submit(scene_sha256=job["settings"]["environment"], settings={"max_spp": 1})
    assert err.value.status == 404 and "no stored scene" in err.value.message
    parts["environment"] = ("sky.png", b"\x89PNG\r\n\x1a\n" + b"0" * 32, "image/png")
    r = client.http.post("/api/v1/jobs", files=parts)
    assert r.status_code == 400 and r.json()["field"] == "environment"


def test_delete_needs_a_finished_job_and_removes_its_data(client):
    job = client.submit(CORNELL, settings={"width": 16, "height": 16, "max_spp": 1})
    r = client.http.delete(f"/api/v1/jobs/{job['id']}")
    if r.status_code == 409:  # still rendering: it must be cancelled first
        assert "cancel" in r.json()["detail"]
        client.cancel(job["id"])
        r = client.http.delete(f"/api/v1/jobs/{job['id']}")
    assert r.status_code == 204, r.text
    with pytest.raises(ApiError) as err:
        client.get(job["id"])
    assert err.value.status == 404
    assert client.http.get(f"/api/v1/jobs/{job['id']}/events").status_code == 404
    assert client.http.delete(f"/api/v1/jobs/{job['id']}").status_code == 404


def test_environment_map_job_equals_the_standalone_render(client, worker_binary, tmp_path):
    """An uploaded environment map reaches the workers (fetched by hash like a scene) and lights
    the scene exactly as the standalone renderer's --environment does."""
    hdr = tmp_path / "sky.hdr"
    _tiny_hdr(hdr)
    settings = {"width": 24, "height": 24, "tile_size": 8, "max_spp": 8, "noise_threshold": 0}
    settings |= {"seed": 2, "environment": str(hdr), "environment_intensity": 3.0}
    job = client.submit(CORNELL, settings=settings)
    job = client.wait(job["id"], poll_s=0.1, timeout_s=300)
    assert job["state"] == "completed", job["error"]
    farm_exr = tmp_path / "farm.exr"
    farm_exr.write_bytes(client.image(job["id"], "exr"))
    alone, plain = tmp_path / "alone.exr", tmp_path / "plain.exr"
    common = [worker_binary, "render", str(CORNELL), "--width", "24", "--height", "24"]
    common += ["--spp", "8", "--seed", "2"]
    sky = ["--environment", str(hdr), "--environment-intensity", "3"]
    subprocess.run([*common, "-o", str(alone), *sky], check=True, capture_output=True, timeout=300)
    np.testing.assert_allclose(_rgb(farm_exr), _rgb(alone), rtol=1e-6, atol=1e-7)
    subprocess.run([*common, "-o", str(plain)], check=True, capture_output=True, timeout=300)
    # The open front of the box lets the sky in: the environment adds light.
    assert _rgb(alone).mean() > _rgb(plain).mean()


def test_grpc_tells_an_explicit_zero_from_an_unset_setting(farm, cornell_job, client):
    """RenderSettings fields are proto3 `optional`: noise_threshold 0 (render max_spp
    everywhere) is not mistaken for "use the default" (0.02)."""
    job, _ = cornell_job
    with grpc.insecure_channel(farm.grpc_address) as channel:
        stub = jobs_pb2_grpc.JobServiceStub(channel)
        settings = jobs_pb2.RenderSettings(noise_threshold=0.0, max_spp=1, width=8, height=8)
        got = stub.SubmitJob(
            jobs_pb2.SubmitJobRequest(scene_sha256=job["scene_sha256"], settings=settings),
            timeout=10,
        ).job
        unset = stub.SubmitJob(
            jobs_pb2.SubmitJobRequest(
                scene_sha256=job["scene_sha256"],
                settings=jobs_pb2.RenderSettings(max_spp=1, width=8, height=8),
            ),
            timeout=10,
        ).job
    assert got.settings.noise_threshold == 0.0
    assert unset.settings.noise_threshold == pytest.approx(0.02)
    for j in (got, unset):
        client.cancel(j.id)
