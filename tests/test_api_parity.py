"""Every JobService operation through REST and through gRPC on the same farm: the same jobs,
the same images, and for each invalid input the same error class naming the same field."""

from __future__ import annotations

import json

import pytest

from renderfarm.v1 import jobs_pb2

from .apihelpers import (
    TINY,
    Apis,
    Error,
    comparable,
    cornell_glb,
    escaping_zip,
    job_from_proto,
    settings_message,
)
from .test_cryptomatte_farm import SETTINGS as CRYPTO_SETTINGS
from .test_cryptomatte_farm import scene as crypto_scene
from .waiting import wait_until


@pytest.fixture(scope="module")
def apis(farm):
    a = Apis(farm.url, farm.grpc_address)
    wait_until(lambda: len(a.client.workers()) >= 2, 30, "2 workers connected")
    yield a
    a.close()


@pytest.fixture(scope="module")
def twin_jobs(apis):
    """The same tiny render submitted once through each API, both finished."""
    glb = cornell_glb()
    via_rest = apis.submit_rest(glb, "cornell.glb", TINY, "parity")
    via_grpc = apis.submit_rpc(glb, "cornell.glb", TINY, "parity")
    assert not isinstance(via_rest, Error), via_rest
    assert not isinstance(via_grpc, Error), via_grpc
    for job in (via_rest, via_grpc):
        apis.client.wait(job["id"], poll_s=0.2, timeout_s=300)
    return via_rest, via_grpc


def test_submit_answers_agree(twin_jobs):
    via_rest, via_grpc = twin_jobs
    a, b = comparable(via_rest), comparable(via_grpc)
    for key in ("id", "created_unix_s"):
        a.pop(key), b.pop(key)
    assert a == b
    assert via_rest["owner"] == via_grpc["owner"] == ""


def test_get_agrees_for_the_same_job(apis, twin_jobs):
    for job in twin_jobs:
        rest = apis.rest("GET", f"/api/v1/jobs/{job['id']}")
        rpc = job_from_proto(apis.rpc("GetJob", jobs_pb2.GetJobRequest(job_id=job["id"])).job)
        assert rest["state"] == "completed", rest
        assert comparable(rest, volatile=False) == comparable(rpc, volatile=False)


def test_list_filters_and_pages_alike(apis, twin_jobs):
    # The state filter reads the stored state, written right after the job finished in memory.
    wait_until(
        lambda: (
            {j["id"] for j in twin_jobs}
            <= {j["id"] for j in apis.client.list(state="completed", page_size=500)["jobs"]}
        ),
        20,
        "the finished jobs to be listed as completed",
        poll_s=0.2,
    )
    pages_rest, pages_rpc = [], []
    token = ""
    for _ in range(50):  # bounded: at most 50 pages of 1
        page = apis.rest("GET", "/api/v1/jobs", params={"state": "completed", "page_size": 1,
                                                         "page_token": token})  # fmt: skip
        pages_rest += [j["id"] for j in page["jobs"]]
        token = page["next_page_token"]
        if not token:
            break
    token = ""
    for _ in range(50):
        page = apis.rpc("ListJobs", jobs_pb2.ListJobsRequest(
            state=jobs_pb2.JOB_STATE_COMPLETED, page_size=1, page_token=token))  # fmt: skip
        pages_rpc += [j.id for j in page.jobs]
        token = page.next_page_token
        if not token:
            break
    assert pages_rest == pages_rpc
    assert {j["id"] for j in twin_jobs} <= set(pages_rest)


def test_images_are_identical_through_both_apis_and_both_submissions(apis, twin_jobs):
    for fmt, enum, layer in (("png", jobs_pb2.IMAGE_FORMAT_PNG, "rgb"),
                             ("png", jobs_pb2.IMAGE_FORMAT_PNG, "error"),
                             ("exr", jobs_pb2.IMAGE_FORMAT_EXR, "")):  # fmt: skip
        images = []
        for job in twin_jobs:
            rest = apis.rest("GET", f"/api/v1/jobs/{job['id']}/image.{fmt}",
                             params={"layer": layer or "rgb"})  # fmt: skip
            rpc = apis.rpc("GetImage", jobs_pb2.GetImageRequest(job_id=job["id"], format=enum,
                                                                 layer=layer))  # fmt: skip
            assert rest == rpc.data and len(rest) > 100
            images.append(rest)
        if fmt == "png":  # same scene, settings and seed: the same picture (PNG is deterministic)
            assert images[0] == images[1]


def test_frame_cameras_agree(apis, twin_jobs):
    """camera.json and GetFrameCamera: the same camera, the matrices row by row, a still's
    camera being frame 0 (and the first image when GetFrameCamera names no frame)."""
    for job in twin_jobs:
        rest = apis.rest("GET", f"/api/v1/jobs/{job['id']}/frames/0/camera.json")
        rpc = apis.rpc("GetFrameCamera", jobs_pb2.GetFrameCameraRequest(job_id=job["id"]))
        c = rpc.camera
        assert (c.frame, c.projection, c.width, c.height) == (
            rest["frame"], rest["projection"], rest["width"], rest["height"])  # fmt: skip
        assert [c.fx, c.fy, c.cx, c.cy, c.near] == [rest[k] for k in ("fx", "fy", "cx", "cy",
                                                                      "near")]  # fmt: skip
        assert list(c.world_to_camera) == [v for row in rest["world_to_camera"] for v in row]
        assert c.HasField("yfov") and c.yfov == rest["yfov"] and not c.HasField("time_s")
        assert rest["time_s"] is None and rest["node"] == c.node


def test_pixel_mattes_agree(apis, tmp_path):
    """GET .../mattes and GetPixelMattes name the same nodes, materials and root nodes with the
    same coverage (the scene of tests/test_cryptomatte_farm.py: the wheel, the lamp, nothing),
    and refuse a pixel outside the image alike."""
    path = tmp_path / "car.gltf"
    path.write_text(json.dumps(crypto_scene()))
    job = apis.client.submit(str(path), settings={**CRYPTO_SETTINGS, "max_spp": 4})
    assert apis.client.wait(job["id"], poll_s=0.2, timeout_s=300)["state"] == "completed"
    for x, y, first in ((12, 24, "wheel"), (8, 5, "lamp"), (40, 2, None)):
        rest = apis.rest("GET", f"/api/v1/jobs/{job['id']}/frames/0/mattes",
                         params={"x": x, "y": y})  # fmt: skip
        rpc = apis.rpc("GetPixelMattes", jobs_pb2.GetPixelMattesRequest(job_id=job["id"], x=x,
                                                                         y=y))  # fmt: skip
        assert (rpc.x, rpc.y, rpc.samples) == (rest["x"], rest["y"], rest["samples"]) == (x, y, 4)
        for key in ("objects", "materials", "assets"):
            got = [{"name": m.name, "id": m.id, "coverage": m.coverage} for m in getattr(rpc, key)]
            assert got == rest[key], key
        assert [m["name"] for m in rest["objects"]][:1] == ([first] if first else [])
    outside = (apis.rest("GET", f"/api/v1/jobs/{job['id']}/frames/0/mattes",
                         params={"x": 0, "y": 999}),
               apis.rpc("GetPixelMattes", jobs_pb2.GetPixelMattesRequest(job_id=job["id"], x=0,
                                                                         y=999)))  # fmt: skip
    assert all(isinstance(e, Error) and (e.kind, e.field) == ("invalid", "y") for e in outside)


def test_watch_streams_end_in_the_same_final_state(apis, twin_jobs):
    job = twin_jobs[0]
    with_sse = list(apis.client.watch(job["id"], timeout_s=60))
    with_grpc = apis.watch_rpc(job["id"])
    assert with_sse[-1]["state"] == with_grpc[-1]["state"] == "completed"
    assert comparable(with_sse[-1], volatile=False) == comparable(with_grpc[-1], volatile=False)


def test_workers_and_scenes_agree(apis, twin_jobs):
    rest = apis.rest("GET", "/api/v1/workers")
    rpc = apis.rpc("ListWorkers", jobs_pb2.ListWorkersRequest())
    assert sorted(w["id"] for w in rest) == sorted(w.id for w in rpc.workers)
    assert {w["id"]: w["cores"] for w in rest} == {w.id: w.cores for w in rpc.workers}
    rest = apis.rest("GET", "/api/v1/replicas")
    rpc = apis.rpc("ListReplicas", jobs_pb2.ListReplicasRequest())
    assert [r["id"] for r in rest] == [r.id for r in rpc.replicas] and len(rest) == 1
    assert [r["jobs_owned"] for r in rest] == [r.jobs_owned for r in rpc.replicas]
    assert rest[0]["addresses"] == dict(rpc.replicas[0].addresses)
    sha = twin_jobs[0]["scene_sha256"]
    scene_rest = apis.rest("GET", f"/api/v1/scenes/{sha}")
    scene_rpc = apis.scene_rpc(sha).scene
    assert scene_rest["sha256"] == scene_rpc.sha256 == sha
    assert scene_rest["size_bytes"] == scene_rpc.size_bytes
    assert scene_rest["format"] == "glb"


def test_submit_by_stored_scene_hash_through_both(apis, twin_jobs):
    sha = twin_jobs[0]["scene_sha256"]
    rest = apis.rest("POST", "/api/v1/jobs", json={"scene_sha256": sha, "settings": TINY})
    rpc = apis.rpc("SubmitJob", jobs_pb2.SubmitJobRequest(
        scene_sha256=sha, settings=settings_message(TINY)))  # fmt: skip
    assert rest["scene_sha256"] == rpc.job.scene_sha256 == sha
    for job_id in (rest["id"], rpc.job.id):
        apis.client.wait(job_id, poll_s=0.2, timeout_s=300)


def test_cancel_then_delete_through_both(apis):
    glb = cornell_glb()
    big = {**TINY, "width": 256, "height": 256, "max_spp": 100000, "noise_threshold": 0.0001}
    jobs = [apis.submit_rest(glb, "big.glb", big, "to cancel"),
            apis.submit_rpc(glb, "big.glb", big, "to cancel")]  # fmt: skip
    # Deleting a running job is a conflict through both APIs.
    rest = apis.rest("DELETE", f"/api/v1/jobs/{jobs[0]['id']}")
    rpc = apis.rpc("DeleteJob", jobs_pb2.DeleteJobRequest(job_id=jobs[1]["id"]))
    assert isinstance(rest, Error) and isinstance(rpc, Error)
    assert rest.kind == rpc.kind == "conflict"
    cancelled_rest = apis.rest("POST", f"/api/v1/jobs/{jobs[0]['id']}/cancel")
    cancelled_rpc = apis.rpc("CancelJob", jobs_pb2.CancelJobRequest(job_id=jobs[1]["id"]))
    assert cancelled_rest["state"] == "cancelled"
    assert job_from_proto(cancelled_rpc.job)["state"] == "cancelled"
    assert apis.rest("DELETE", f"/api/v1/jobs/{jobs[0]['id']}") is None
    assert isinstance(apis.rpc("DeleteJob", jobs_pb2.DeleteJobRequest(job_id=jobs[1]["id"])),
                      jobs_pb2.DeleteJobResponse)  # fmt: skip
    for job in jobs:
        gone_rest = apis.rest("GET", f"/api/v1/jobs/{job['id']}")
        gone_rpc = apis.rpc("GetJob", jobs_pb2.GetJobRequest(job_id=job["id"]))
        assert gone_rest.kind == gone_rpc.kind == "not_found"


INVALID_SUBMISSIONS = [
    ("width over the limit", {"width": 100000}, "glb", "", "invalid",
     "settings.width"),
    ("unknown sampler", {"sampler": "magic"}, "glb", "", "invalid", "settings.sampler"),
    ("spp over the limit", {"max_spp": 2**30}, "glb", "", "invalid", "settings.max_spp"),
    ("tile too small", {"tile_size": 4}, "glb", "", "invalid", "settings.tile_size"),
    ("noise threshold out of range", {"noise_threshold": 50.0}, "glb", "", "invalid",
     "settings.noise_threshold"),
    ("min_spp above max_spp", {"min_spp": 64, "max_spp": 8}, "glb", "", "invalid",
     "settings.min_spp"),
    ("non-glTF content", {}, "png", "", "invalid", "scene"),
    ("bundle with ../", {}, "escaping-zip", "", "invalid", "scene"),
    ("empty scene", {}, "empty", "", "invalid", "scene"),
]  # fmt: skip


def _scene(kind: str) -> tuple[bytes, str]:
    if kind == "glb":
        return cornell_glb(), "cornell.glb"
    if kind == "png":
        return b"\x89PNG\r\n\x1a\n" + bytes(100), "picture.png"
    if kind == "escaping-zip":
        return escaping_zip(), "bundle.zip"
    return b"", "empty.glb"


@pytest.mark.parametrize("case", INVALID_SUBMISSIONS, ids=[c[0] for c in INVALID_SUBMISSIONS])
def test_invalid_submissions_are_refused_alike(apis, case):
    _, settings, scene, _, kind, field = case
    data, filename = _scene(scene)
    rest = apis.submit_rest(data, filename, settings, "bad")
    rpc = apis.submit_rpc(data, filename, settings, "bad") if data else apis.rpc(
        "SubmitJob", jobs_pb2.SubmitJobRequest(scene_filename=filename))  # fmt: skip
    assert isinstance(rest, Error) and isinstance(rpc, Error), (rest, rpc)
    assert (rest.kind, rest.field) == (kind, field), rest
    assert (rpc.kind, rpc.field) == (kind, field), rpc


def test_invalid_lookups_are_refused_alike(apis, twin_jobs):
    done = twin_jobs[0]["id"]
    pairs = [
        (apis.rest("GET", "/api/v1/jobs/ffffffffffff"),
         apis.rpc("GetJob", jobs_pb2.GetJobRequest(job_id="ffffffffffff")), "not_found", ""),
        (apis.rest("GET", "/api/v1/jobs/not a job id!"),
         apis.rpc("GetJob", jobs_pb2.GetJobRequest(job_id="not a job id!")), "not_found", ""),
        (apis.rest("POST", "/api/v1/jobs/ffffffffffff/cancel"),
         apis.rpc("CancelJob", jobs_pb2.CancelJobRequest(job_id="ffffffffffff")), "not_found",
         ""),
        (apis.rest("GET", f"/api/v1/jobs/{done}/image.png", params={"layer": "bogus"}),
         apis.rpc("GetImage", jobs_pb2.GetImageRequest(job_id=done, layer="bogus")), "invalid",
         "layer"),
        (apis.rest("GET", "/api/v1/jobs", params={"page_token": "garbage"}),
         apis.rpc("ListJobs", jobs_pb2.ListJobsRequest(page_token="garbage")), "invalid",
         "page_token"),
        (apis.rest("POST", "/api/v1/jobs", json={"scene_sha256": "abc"}),
         apis.rpc("SubmitJob", jobs_pb2.SubmitJobRequest(scene_sha256="abc")), "invalid",
         "scene_sha256"),
        (apis.rest("POST", "/api/v1/jobs", json={"scene_sha256": "0" * 64}),
         apis.rpc("SubmitJob", jobs_pb2.SubmitJobRequest(scene_sha256="0" * 64)), "not_found",
         ""),
        (apis.rest("GET", "/api/v1/scenes/" + "0" * 64), apis.scene_rpc("0" * 64), "not_found",
         ""),
        (apis.rest("GET", f"/api/v1/jobs/{done}/frames/5/camera.json"),
         apis.rpc("GetFrameCamera", jobs_pb2.GetFrameCameraRequest(job_id=done, frame=5)),
         "not_found", "frame"),
        # A job without settings.aovs naming cryptomatte has no mattes.
        (apis.rest("GET", f"/api/v1/jobs/{done}/frames/0/mattes", params={"x": 0, "y": 0}),
         apis.rpc("GetPixelMattes", jobs_pb2.GetPixelMattesRequest(job_id=done, x=0, y=0)),
         "invalid", "layer"),
    ]  # fmt: skip
    for rest, rpc, kind, field in pairs:
        assert isinstance(rest, Error) and isinstance(rpc, Error), (rest, rpc)
        assert (rest.kind, rest.field) == (rpc.kind, rpc.field) == (kind, field), (rest, rpc)


def test_job_control_is_refused_alike(apis, twin_jobs):
    done = twin_jobs[0]["id"]  # completed
    sha = twin_jobs[0]["scene_sha256"]
    rs = jobs_pb2.RenderSettings
    pairs = [
        (apis.rest("POST", f"/api/v1/jobs/{done}/pause"),
         apis.rpc("PauseJob", jobs_pb2.PauseJobRequest(job_id=done)), "conflict", ""),
        (apis.rest("POST", f"/api/v1/jobs/{done}/resume"),
         apis.rpc("ResumeJob", jobs_pb2.ResumeJobRequest(job_id=done)), "conflict", ""),
        (apis.rest("POST", f"/api/v1/jobs/{done}/retry"),
         apis.rpc("RetryJob", jobs_pb2.RetryJobRequest(job_id=done)), "conflict", ""),
        (apis.rest("POST", "/api/v1/jobs/ffffffffffff/pause"),
         apis.rpc("PauseJob", jobs_pb2.PauseJobRequest(job_id="ffffffffffff")), "not_found", ""),
        (apis.rest("PATCH", f"/api/v1/jobs/{done}", json={"priority": 5000}),
         apis.rpc("UpdateJob", jobs_pb2.UpdateJobRequest(job_id=done, priority=5000)),
         "invalid", "priority"),
        (apis.rest("PATCH", f"/api/v1/jobs/{done}", json={"name": "a\x01b"}),
         apis.rpc("UpdateJob", jobs_pb2.UpdateJobRequest(job_id=done, name="a\x01b")),
         "invalid", "name"),
        (apis.rest("POST", f"/api/v1/jobs/{done}/continue", json={"settings": {"width": 8}}),
         apis.rpc("ContinueJob", jobs_pb2.ContinueJobRequest(job_id=done, settings=rs(width=8))),
         "invalid", "settings.width"),
        (apis.rest("POST", f"/api/v1/jobs/{done}/continue", json={"settings": {"max_spp": 2}}),
         apis.rpc("ContinueJob", jobs_pb2.ContinueJobRequest(job_id=done, settings=rs(max_spp=2))),
         "invalid", "settings.max_spp"),
        (apis.rest("POST", f"/api/v1/jobs/{done}/continue",
                   json={"settings": {"noise_threshold": 0.5}}),
         apis.rpc("ContinueJob", jobs_pb2.ContinueJobRequest(
             job_id=done, settings=rs(noise_threshold=0.5))), "invalid",
         "settings.noise_threshold"),
        (apis.rest("POST", "/api/v1/jobs", json={"scene_sha256": sha, "after": ["0" * 12]}),
         apis.rpc("SubmitJob", jobs_pb2.SubmitJobRequest(scene_sha256=sha, after=["0" * 12])),
         "invalid", "after"),
        (apis.rest("POST", "/api/v1/jobs", json={"scene_sha256": sha, "after": ["not an id!"]}),
         apis.rpc("SubmitJob", jobs_pb2.SubmitJobRequest(scene_sha256=sha, after=["not an id!"])),
         "invalid", "after"),
    ]  # fmt: skip
    for rest, rpc, kind, field in pairs:
        assert isinstance(rest, Error) and isinstance(rpc, Error), (rest, rpc)
        assert (rest.kind, rest.field) == (rpc.kind, rpc.field) == (kind, field), (rest, rpc)


def test_update_and_continue_through_both_alike(apis, twin_jobs):
    """Last in this module: it renames and continues the twin jobs."""
    via_rest, via_grpc = twin_jobs
    a = apis.rest("PATCH", f"/api/v1/jobs/{via_rest['id']}", json={"priority": 3, "name": "r"})
    b = job_from_proto(apis.rpc("UpdateJob", jobs_pb2.UpdateJobRequest(
        job_id=via_grpc["id"], priority=3, name="r")).job)  # fmt: skip
    assert (a["settings"]["priority"], a["name"]) == (b["settings"]["priority"], b["name"]) == (
        3, "r")  # fmt: skip
    settings = {"max_spp": 12}
    a = apis.rest("POST", f"/api/v1/jobs/{via_rest['id']}/continue", json={"settings": settings})
    b = job_from_proto(apis.rpc("ContinueJob", jobs_pb2.ContinueJobRequest(
        job_id=via_grpc["id"], settings=settings_message(settings))).job)  # fmt: skip
    assert a["settings"]["max_spp"] == b["settings"]["max_spp"] == 12
    a = apis.client.wait(a["id"], poll_s=0.2, timeout_s=300)
    b = apis.client.wait(b["id"], poll_s=0.2, timeout_s=300)
    assert a["state"] == b["state"] == "completed"
    assert a["progress"]["samples_merged"] == b["progress"]["samples_merged"]
    assert apis.client.image(a["id"], "exr") != b""
    png = [apis.rest("GET", f"/api/v1/jobs/{j['id']}/image.png") for j in (a, b)]
    assert png[0] == png[1]
    kinds = [e["kind"] for e in apis.client.events(a["id"])]
    assert "job_updated" in kinds and "job_continued" in kinds
