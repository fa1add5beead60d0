"""Camera data per frame (#40): camera.json, the EXR header's worldToCamera and worldToNDC, and
the gRPC GetFrameCamera, held to a scene made here whose camera is known: a glTF camera at a
known position and orientation with a known yfov (or xmag, ymag), moved by an animation a known
amount between frames. Expected values come from numpy and the pinhole formula on the scene's
own numbers, never from the code under test; the projection test renders the scene with the
worker and finds the small emissive square where the published camera projects it."""

from __future__ import annotations

import asyncio
import base64
import json
import math
import subprocess
from pathlib import Path

import grpc
import httpx
import numpy as np
import pytest

from renderfarm.api.grpc_api import start_grpc
from renderfarm.api.rest import create_app
from renderfarm.app.auth import Authenticator, Caller
from renderfarm.app.composition import build_farm_service
from renderfarm.errors import NotFound
from renderfarm.infra.config import Settings
from renderfarm.infra.memory_store import MemoryStore
from renderfarm.infra.worker_binary import find_worker_binary
from renderfarm.v1 import jobs_pb2, jobs_pb2_grpc

ADMIN = Caller("", True)
W, H = 64, 48
YFOV = 0.8
XMAG, YMAG = 2.4, 1.5  # orthographic: 4.8 x 3 units on a 4:3 image, pixels not square
FPS = 24.0
T0 = np.array([0.5, 1.0, 4.0])  # the camera's translation at t = 0 ...
T1 = np.array([1.7, 0.4, 3.2])  # ... and at t = 1 (LINEAR), held after
# The point the emissive square is centred on, in frame 0's camera space (x right, y up, -z
# ahead): off the axis on both sides, so cx, cy and the signs count.
AT_CAMERA = np.array([0.9, -0.5, -5.0])
HALF = 0.5  # half the square's side: 11 pixels across (perspective), the edges' share of the
# centroid small (a pixel partly covered counts at its centre)


def axis_angle(axis, angle):
    """(quaternion x, y, z, w; rotation matrix), each from its own textbook formula."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    q = np.append(axis * math.sin(angle / 2), math.cos(angle / 2))
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    r = np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k  # Rodrigues
    return q, r


def hamilton(a, b):
    (x1, y1, z1, w1), (x2, y2, z2, w2) = a, b
    return np.array([
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
    ])  # fmt: skip


Q_YAW, R_YAW = axis_angle([0, 1, 0], math.radians(35))
Q_PITCH, R_PITCH = axis_angle([1, 0, 0], math.radians(-15))
ROTATION_Q = hamilton(Q_YAW, Q_PITCH)  # yaw after pitch
ROTATION = R_YAW @ R_PITCH
POINT = T0 + ROTATION @ AT_CAMERA  # the square's centre, world space


def translation_at(t: float) -> np.ndarray:
    return T0 + (T1 - T0) * min(max(t, 0.0), 1.0)


def camera_to_world_at(t: float | None) -> np.ndarray:
    """The camera node's TRS (scale 1) as a 4x4 matrix: T R."""
    m = np.eye(4)
    m[:3, :3] = ROTATION
    m[:3, 3] = T0 if t is None else translation_at(t)
    return m


def scene(projection: str) -> dict:
    """A self-contained glTF: the camera node (animated translation) and a small emissive
    square at POINT, facing the camera, on a black background."""
    right, up = ROTATION[:, 0], ROTATION[:, 1]
    signs = ((-1, -1), (1, -1), (1, 1), (-1, 1))
    corners = [POINT + HALF * (sx * right + sy * up) for sx, sy in signs]
    positions = np.array(corners, np.float32)
    indices = np.array([0, 1, 2, 0, 2, 3], np.uint16)
    times = np.array([0.0, 1.0], np.float32)
    moves = np.array([T0, T1], np.float32)
    blob = positions.tobytes() + indices.tobytes() + times.tobytes() + moves.tobytes()
    views = [(0, 48), (48, 12), (60, 8), (68, 24)]
    perspective = {"yfov": YFOV, "aspectRatio": 2.0, "znear": 0.05, "zfar": 100.0}
    orthographic = {"xmag": XMAG, "ymag": YMAG, "znear": 0.1, "zfar": 50.0}
    camera = (
        {"type": "perspective", "perspective": perspective}
        if projection == "perspective"
        else {"type": "orthographic", "orthographic": orthographic}
    )
    return {
        "asset": {"version": "2.0"},
        "extensionsUsed": ["KHR_materials_variants"],
        "extensions": {"KHR_materials_variants": {"variants": [{"name": "A"}, {"name": "B"}]}},
        "scene": 0,
        "scenes": [{"nodes": [0, 1]}],
        "nodes": [
            {
                "name": "camera",
                "camera": 0,
                "translation": T0.tolist(),
                "rotation": ROTATION_Q.tolist(),
            },
            {"name": "square", "mesh": 0},
        ],
        "cameras": [camera],
        "meshes": [
            {
                "primitives": [
                    {
                        "attributes": {"POSITION": 0},
                        "indices": 1,
                        "material": 0,
                        "extensions": {
                            "KHR_materials_variants": {
                                "mappings": [{"material": 1, "variants": [1]}]
                            }
                        },
                    }
                ]
            }
        ],
        "materials": [
            {
                "emissiveFactor": [1, 1, 1],
                "doubleSided": True,
                "pbrMetallicRoughness": {"baseColorFactor": [0, 0, 0, 1]},
            },
            {
                "emissiveFactor": [0, 1, 0],
                "doubleSided": True,
                "pbrMetallicRoughness": {"baseColorFactor": [0, 0, 0, 1]},
            },
        ],
        "animations": [
            {
                "samplers": [{"input": 2, "output": 3, "interpolation": "LINEAR"}],
                "channels": [{"sampler": 0, "target": {"node": 0, "path": "translation"}}],
            }
        ],
        "buffers": [
            {
                "byteLength": len(blob),
                "uri": "data:application/octet-stream;base64," + base64.b64encode(blob).decode(),
            }
        ],
        "bufferViews": [{"buffer": 0, "byteOffset": o, "byteLength": n} for o, n in views],
        "accessors": [
            {
                "bufferView": 0,
                "componentType": 5126,
                "count": 4,
                "type": "VEC3",
                "min": positions.min(0).tolist(),
                "max": positions.max(0).tolist(),
            },
            {"bufferView": 1, "componentType": 5123, "count": 6, "type": "SCALAR"},
            {
                "bufferView": 2,
                "componentType": 5126,
                "count": 2,
                "type": "SCALAR",
                "min": [0.0],
                "max": [1.0],
            },
            {"bufferView": 3, "componentType": 5126, "count": 2, "type": "VEC3"},
        ],
    }


def scene_bytes(projection: str) -> bytes:
    return json.dumps(scene(projection)).encode()


def pinhole(point: np.ndarray, t: float | None, projection: str) -> tuple[float, float]:
    """Where the point lands in the image (pixels from the top-left corner, +v down), from the
    scene's own numbers: the inverse of the camera's TRS and the textbook pinhole (fy =
    (H/2) / tan(yfov/2), square pixels) or orthographic (W / 2 xmag, H / 2 ymag) mapping."""
    x, y, z, _ = np.linalg.inv(camera_to_world_at(t)) @ np.append(point, 1.0)
    if projection == "perspective":
        f = (H / 2) / math.tan(YFOV / 2)
        return W / 2 + f * x / -z, H / 2 - f * y / -z
    return W / 2 + W / (2 * XMAG) * x, H / 2 - H / (2 * YMAG) * y


def published_projection(camera: dict, point: np.ndarray) -> tuple[float, float]:
    """The published camera used as its documentation says."""
    x, y, z, _ = np.array(camera["world_to_camera"]) @ np.append(point, 1.0)
    if camera["projection"] == "perspective":
        return camera["cx"] + camera["fx"] * x / -z, camera["cy"] - camera["fy"] * y / -z
    return camera["cx"] + camera["fx"] * x, camera["cy"] - camera["fy"] * y


class Farm:
    """A job service over MemoryStore with the real worker binary as its scene checker (no
    workers: camera data needs none), with its REST app."""

    def __init__(self, tmp_path: Path):
        self.store = MemoryStore()
        self.service = build_farm_service(Settings(data_dir=tmp_path), self.store)

    async def __aenter__(self) -> Farm:
        await self.service.start()
        return self

    async def __aexit__(self, *exc) -> None:
        await self.service.stop(timeout_s=5)

    async def submit(self, projection: str, **settings) -> str:
        raw = {"width": W, "height": H, "max_spp": 1, "fps": FPS, **settings}
        view = await self.service.submit(
            caller=ADMIN, scene_data=scene_bytes(projection), scene_sha256="",
            filename="camera.gltf", name="camera", raw_settings=raw,
        )  # fmt: skip
        return view.id

    def http(self) -> httpx.AsyncClient:
        app = create_app(self.service, None, auth=Authenticator(self.store, loopback_only=True))
        transport = httpx.ASGITransport(app=app, client=("127.0.0.1", 5000))
        return httpx.AsyncClient(transport=transport, base_url="http://test")


FRAMES = (0, 12, 30)  # t = 0, 0.5 (half way) and 1.25 (after the last key: held at T1)


@pytest.mark.parametrize("projection", ["perspective", "orthographic"])
def test_camera_json_is_the_scenes_camera_at_each_frame(tmp_path, projection):
    async def main():
        async with Farm(tmp_path) as farm:
            job = await farm.submit(projection, frames="0,12,30", shutter="-0.25,0.25")
            still = await farm.submit(projection)
            async with farm.http() as http:
                frames = {
                    f: (await http.get(f"/api/v1/jobs/{job}/frames/{f}/camera.json")).json()
                    for f in FRAMES
                }
                still_camera = await http.get(f"/api/v1/jobs/{still}/frames/0/camera.json")
            return frames, still_camera.json()

    frames, still = asyncio.run(main())
    for frame, camera in frames.items():
        t = frame / FPS
        assert camera["frame"] == frame and camera["time_s"] == pytest.approx(t, abs=1e-12)
        assert camera["shutter_s"] == pytest.approx([(frame - 0.25) / FPS, (frame + 0.25) / FPS])
        assert (camera["width"], camera["height"]) == (W, H)
        assert (camera["cx"], camera["cy"]) == (W / 2, H / 2)
        if projection == "perspective":
            focal = (H / 2) / math.tan(YFOV / 2)  # aspectRatio 2.0 is not used: square pixels
            assert camera["fx"] == pytest.approx(focal, rel=1e-6)
            assert camera["fy"] == pytest.approx(focal, rel=1e-6)
            assert camera["yfov"] == pytest.approx(YFOV, rel=1e-6)
            assert (camera["xmag"], camera["ymag"]) == (None, None)
            assert (camera["near"], camera["far"]) == (pytest.approx(0.05), pytest.approx(100))
        else:
            assert camera["fx"] == pytest.approx(W / (2 * XMAG), rel=1e-6)
            assert camera["fy"] == pytest.approx(H / (2 * YMAG), rel=1e-6)
            assert camera["yfov"] is None
            assert (camera["xmag"], camera["ymag"]) == (pytest.approx(XMAG), pytest.approx(YMAG))
            assert (camera["near"], camera["far"]) == (pytest.approx(0.1), pytest.approx(50))
        assert camera["projection"] == projection and camera["node"] == 0
        to_world = np.array(camera["camera_to_world"])
        to_camera = np.array(camera["world_to_camera"])
        np.testing.assert_allclose(to_world, camera_to_world_at(t), atol=2e-6)
        np.testing.assert_allclose(to_camera, np.linalg.inv(camera_to_world_at(t)), atol=2e-6)
        np.testing.assert_allclose(to_camera @ to_world, np.eye(4), atol=1e-9)
        np.testing.assert_allclose(
            published_projection(camera, POINT), pinhole(POINT, t, projection), atol=1e-4
        )
    # The camera moved by the animation's amount between frames 0 and 12, and is held after 1 s.
    at = {f: np.array(frames[f]["camera_to_world"])[:3, 3] for f in FRAMES}
    np.testing.assert_allclose(at[12] - at[0], (T1 - T0) / 2, atol=2e-6)
    np.testing.assert_allclose(at[30], T1, atol=2e-6)
    # A still: the scene as stored (the node's own translation), no time, no shutter.
    assert (still["frame"], still["time_s"], still["shutter_s"]) == (0, None, None)
    still_to_world = np.array(still["camera_to_world"])
    np.testing.assert_allclose(still_to_world, camera_to_world_at(None), atol=2e-6)


def bright_centroid(exr: Path) -> tuple[float, float]:
    """The luminance-weighted centre of the image (pixel (i, j)'s centre at i + 0.5, j + 0.5)."""
    import OpenImageIO as oiio

    pixels = oiio.ImageBuf(str(exr)).get_pixels(oiio.FLOAT)[..., :3].sum(axis=2)
    assert pixels.shape == (H, W) and pixels.max() > 0, "the square is not in the image"
    rows, cols = np.mgrid[0:H, 0:W]
    total = pixels.sum()
    u = (pixels * (cols + 0.5)).sum() / total
    return float(u), float((pixels * (rows + 0.5)).sum() / total)


@pytest.mark.parametrize("projection", ["perspective", "orthographic"])
def test_a_point_projected_with_the_published_camera_is_where_the_renderer_draws_it(
    tmp_path, projection
):
    path = tmp_path / "camera.gltf"
    path.write_bytes(scene_bytes(projection))

    async def cameras():
        async with Farm(tmp_path) as farm:
            job = await farm.submit(projection, frames="0,12")
            return [await farm.service.frame_camera(job, f, ADMIN) for f in (0, 12)]

    for camera in asyncio.run(cameras()):
        out = tmp_path / f"frame{camera['frame']}.exr"
        subprocess.run(
            [find_worker_binary(), "render", str(path), "-o", str(out), "--spp", "64",
             "--width", str(W), "--height", str(H), "--threads", "1",
             "--time", repr(camera["time_s"])],
            check=True, capture_output=True, timeout=120,
        )  # fmt: skip
        u, v = published_projection(camera, POINT)
        found = bright_centroid(out)
        assert found == pytest.approx((u, v), abs=0.03), (camera["frame"], found, (u, v))
    # Not vacuous: the square moved between the frames by more than the tolerance.
    assert abs(pinhole(POINT, 0.0, projection)[0] - pinhole(POINT, 0.5, projection)[0]) > 1


def test_the_exr_header_carries_the_camera(tmp_path):
    import OpenImageIO as oiio

    async def main():
        async with Farm(tmp_path) as farm:
            job = await farm.submit("perspective", frames="0,12")
            exr = await farm.service.image(job, "exr", "rgb", ADMIN, frame=12)
            return exr, await farm.service.frame_camera(job, 12, ADMIN)

    exr, camera = asyncio.run(main())
    (tmp_path / "frame.exr").write_bytes(exr)
    spec = oiio.ImageInput.open(str(tmp_path / "frame.exr")).spec()
    to_camera = np.array(spec.getattribute("worldToCamera")).reshape(4, 4)  # Imath: p' = p M
    to_ndc = np.array(spec.getattribute("worldToNDC")).reshape(4, 4)
    types = {a.name: a.type for a in spec.extra_attribs}
    assert types["worldToCamera"] == types["worldToNDC"] == oiio.TypeMatrix44  # Imath M44f
    assert json.loads(spec.getattribute("renderfarm:camera")) == camera
    position = camera_to_world_at(0.5)[:3, 3]
    ahead = position - 3.0 * ROTATION[:, 2]  # 3 units along the view (glTF's camera -Z)
    np.testing.assert_allclose(np.append(position, 1) @ to_camera, [0, 0, 0, 1], atol=1e-5)
    # OpenEXR's camera space: left-handed, +z the viewing direction, x right, y up.
    np.testing.assert_allclose(np.append(ahead, 1) @ to_camera, [0, 0, 3, 1], atol=1e-5)
    above_right = position + ROTATION[:, 0] + ROTATION[:, 1] - 3.0 * ROTATION[:, 2]
    np.testing.assert_allclose(np.append(above_right, 1) @ to_camera, [1, 1, 3, 1], atol=1e-5)
    # NDC: (0, 0) the top-left corner, (1, 1) the bottom-right, after the divide by w.
    x, y, _, w = np.append(POINT, 1) @ to_ndc
    u, v = pinhole(POINT, 0.5, "perspective")
    assert (x / w, y / w) == pytest.approx((u / W, v / H), abs=1e-6)


def test_rest_status_codes_and_grpc_agree(tmp_path):
    async def main():
        async with Farm(tmp_path) as farm:
            job = await farm.submit("perspective", frames="0,12")
            variants = await farm.submit("perspective", variant="all")
            server, port = await start_grpc(farm.service, "127.0.0.1", 0)
            try:
                async with farm.http() as http:
                    url = f"/api/v1/jobs/{job}/frames/{{}}/camera.json"
                    ok = await http.get(url.format(12))
                    no_frame = await http.get(url.format(5))
                    no_job = await http.get(f"/api/v1/jobs/{'0' * 32}/frames/0/camera.json")
                    variant = [
                        await http.get(f"/api/v1/jobs/{variants}/frames/{f}/camera.json")
                        for f in (0, 1, 2)
                    ]
                async with grpc.aio.insecure_channel(f"127.0.0.1:{port}") as channel:
                    stub = jobs_pb2_grpc.JobServiceStub(channel)
                    rpc = await stub.GetFrameCamera(
                        jobs_pb2.GetFrameCameraRequest(job_id=job, frame=12)
                    )
                    try:
                        await stub.GetFrameCamera(
                            jobs_pb2.GetFrameCameraRequest(job_id=job, frame=5)
                        )
                        rpc_missing = None
                    except grpc.aio.AioRpcError as e:
                        rpc_missing = (e.code(), dict(e.trailing_metadata() or ()))
            finally:
                await server.stop(None)
            with pytest.raises(NotFound):
                await farm.service.frame_camera(job, 1, ADMIN)
            return ok, no_frame, no_job, variant, rpc, rpc_missing

    ok, no_frame, no_job, variant, rpc, rpc_missing = asyncio.run(main())
    assert ok.status_code == 200 and ok.json()["frame"] == 12
    assert no_frame.status_code == 404 and no_frame.json()["field"] == "frame"
    assert "frames are 0,12" in no_frame.json()["detail"]
    assert no_job.status_code == 404
    # A job of every variant: one image per variant (frames 0, 1), posed as stored.
    assert [r.status_code for r in variant] == [200, 200, 404]
    assert variant[0].json()["time_s"] is None
    assert variant[0].json()["world_to_camera"] == variant[1].json()["world_to_camera"]
    # gRPC: the same camera, matrices row by row; the same error and field.
    c = rpc.camera
    body = ok.json()
    assert (c.frame, c.projection, c.width, c.height) == (12, "perspective", W, H)
    assert (c.fx, c.fy, c.cx, c.cy, c.yfov, c.near) == tuple(
        body[k] for k in ("fx", "fy", "cx", "cy", "yfov", "near")
    )
    assert c.time_s == body["time_s"] and c.far == body["far"] and c.node == body["node"]
    assert not c.HasField("xmag") and list(c.shutter_s) == []
    assert list(c.world_to_camera) == [v for row in body["world_to_camera"] for v in row]
    assert list(c.camera_to_world) == [v for row in body["camera_to_world"] for v in row]
    assert rpc_missing == (grpc.StatusCode.NOT_FOUND, {"renderfarm-field": "frame"})


def test_the_loader_is_run_once_for_frames_asked_at_once(tmp_path):
    """Camera data is kept per (job, frame); the frames of an animation are posed together, and
    requests that come while they are posed wait for that one run."""

    async def main():
        async with Farm(tmp_path) as farm:
            checker = farm.service.scene_checker
            calls = []
            real = checker.cameras

            async def counted(*args, **kwargs):
                calls.append(args[2])
                return await real(*args, **kwargs)

            checker.cameras = counted
            job = await farm.submit("perspective", frames="0-40")
            first = await asyncio.gather(
                *(farm.service.frame_camera(job, f, ADMIN) for f in (0, 5, 31, 33))
            )
            again = await farm.service.frame_camera(job, 5, ADMIN)
            return calls, first, again

    calls, first, again = asyncio.run(main())
    # Frames 0..15 in one run, 16..31 and 32..40 in two more; none asked twice.
    runs = [range(16), range(16, 32), range(32, 41)]
    assert sorted(calls) == [[f / FPS for f in frames] for frames in runs]
    assert [c["frame"] for c in first] == [0, 5, 31, 33] and again == first[1]
