"""The outputs of settings.aovs on a real farm (#40): depth and position of a scene whose answer is
known. A camera at a known place, turned a known way, sees a plane facing it at a known distance
(bottom left), nothing (top left) and a plane tilted about its horizontal axis (right half). The
expected values come from the pinhole geometry of the scene's own numbers in numpy: the depth is
the distance along the viewing axis (Blender's Depth pass), so it is the same over the facing
plane although the rays to its corners are longer; the position is the world-space point, which
the camera's inverse transform (numpy) takes back onto the plane, inside the pixel's footprint."""

from __future__ import annotations

import base64
import json
import math

import numpy as np
import pytest

from renderfarm.client import ApiError, Client
from renderfarm.infra.images import read_exr

from .waiting import wait_until

W, H = 32, 24
YFOV = 0.8
TAN = math.tan(YFOV / 2)
NEAR_PLANE = 3.0  # the facing plane: camera-space z = -3 (bottom left quadrant)
TILT = 0.3  # the tilted plane: z = -(4 + TILT y) in camera space (right half)
CAMERA_AT = np.array([1.0, 2.0, 5.0])
SETTINGS = {"width": W, "height": H, "tile_size": 16, "max_spp": 4, "noise_threshold": 0,
            "aovs": ["depth", "position"]}  # fmt: skip


def rotation(axis, angle: float) -> np.ndarray:
    """Rodrigues' formula."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


R = rotation([1.0, 2.0, 0.5], 0.6)


def quaternion(r: np.ndarray) -> list[float]:
    """(x, y, z, w) of a rotation matrix (its trace is positive here)."""
    w = math.sqrt(1 + np.trace(r)) / 2
    return [(r[2, 1] - r[1, 2]) / (4 * w), (r[0, 2] - r[2, 0]) / (4 * w),
            (r[1, 0] - r[0, 1]) / (4 * w), w]  # fmt: skip


def to_world(camera_points: np.ndarray) -> np.ndarray:
    return camera_points @ R.T + CAMERA_AT


def to_camera(world_points: np.ndarray) -> np.ndarray:
    return (world_points - CAMERA_AT) @ R


DATA_URI = "data:application/octet-stream;base64,"


def scene() -> dict:
    """The two planes as quads in camera space, placed in the world with the camera's transform
    (so the world positions are not the camera-space ones)."""
    facing = [(-10, -10, -NEAR_PLANE), (0, -10, -NEAR_PLANE), (0, 0, -NEAR_PLANE),
              (-10, 0, -NEAR_PLANE)]  # fmt: skip
    tilted = [(0, y, -(4 + TILT * y)) for y in (-6, 6)]
    tilted = [tilted[0], (10, *tilted[0][1:]), (10, *tilted[1][1:]), tilted[1]]
    positions = to_world(np.array(facing + tilted, float)).astype(np.float32)
    indices = np.array([0, 1, 2, 0, 2, 3, 4, 5, 6, 4, 6, 7], np.uint16)
    blob = positions.tobytes() + indices.tobytes()
    return {
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0, 1]}],
        "nodes": [
            {"name": "camera", "camera": 0, "translation": CAMERA_AT.tolist(),
             "rotation": quaternion(R)},
            {"name": "planes", "mesh": 0},
        ],  # fmt: skip
        "cameras": [{"type": "perspective",
                     "perspective": {"yfov": YFOV, "aspectRatio": W / H, "znear": 0.05}}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1, "material": 0}]}],
        "materials": [{"emissiveFactor": [1, 1, 1], "doubleSided": True}],
        "buffers": [{"byteLength": len(blob), "uri": DATA_URI + base64.b64encode(blob).decode()}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 96},
                        {"buffer": 0, "byteOffset": 96, "byteLength": 24}],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 8, "type": "VEC3",
             "min": positions.min(0).tolist(), "max": positions.max(0).tolist()},
            {"bufferView": 1, "componentType": 5123, "count": 12, "type": "SCALAR"},
        ],
    }  # fmt: skip


def ray(i: float, j: float) -> tuple[float, float]:
    """Camera-space (a, b) of the ray (a, b, -1) through image point (i, j) (x right from the
    left edge, y down from the top, in pixels): the pinhole formula with square pixels."""
    return (2 * i / W - 1) * TAN * W / H, (1 - 2 * j / H) * TAN


@pytest.fixture(scope="module")
def outputs(farm, tmp_path_factory):
    out = tmp_path_factory.mktemp("aovs")
    path = out / "planes.gltf"
    path.write_text(json.dumps(scene()))
    with Client(farm.url, timeout=120) as client:
        wait_until(lambda: len(client.workers()) >= 1, 30, "a worker connected")
        job = client.submit(str(path), settings=SETTINGS, name="aovs")
        plain = client.submit(str(path), settings={**SETTINGS, "aovs": []}, name="no aovs")
        for j in (job, plain):
            done = client.wait(j["id"], poll_s=0.2, timeout_s=600)
            assert done["state"] == "completed", done
        client.save_image(job["id"], out / "planes.exr", "exr")
        client.save_image(plain["id"], out / "plain.exr", "exr")
        pngs = {
            layer: client.image(job["id"], "png", layer=layer) for layer in ("depth", "position")
        }
        with pytest.raises(ApiError) as refused:
            client.image(plain["id"], "png", layer="depth")
    return job, plain, read_exr(str(out / "planes.exr")), read_exr(str(out / "plain.exr")), \
        pngs, refused.value, out  # fmt: skip


def test_depth_is_the_distance_along_the_viewing_axis_and_background_is_1e10(outputs):
    _, _, exr, _, _, _, _ = outputs
    depth = exr["depth.Z"]
    assert depth.shape == (H, W)
    # Bottom left: the facing plane, one depth everywhere (the rays are up to 1.3 times longer).
    np.testing.assert_allclose(depth[H // 2 :, : W // 2], NEAR_PLANE, rtol=2e-6)
    corner_ray = math.hypot(1, *ray(0, H))
    assert corner_ray > 1.2  # not vacuous: a ray length would differ by 20%
    # Top left: nothing hit.
    assert (depth[: H // 2, : W // 2] == 1e10).all()
    # Right half: the tilted plane; t = 4 / (1 - TILT b) along the axis for a ray of height b,
    # so each pixel's depth lies between the values at its top and bottom edges.
    for j in range(H):
        for i in range(W // 2, W):
            edges = [4 / (1 - TILT * ray(i, y)[1]) for y in (j, j + 1)]
            assert min(edges) * (1 - 2e-6) <= depth[j, i] <= max(edges) * (1 + 2e-6), (i, j)


def test_position_is_the_world_space_point_of_the_first_hit(outputs):
    _, _, exr, _, _, _, _ = outputs
    world = np.stack([exr[f"position.{a}"] for a in "XYZ"], -1).astype(np.float64)
    assert (world[: H // 2, : W // 2] == 0).all()  # nothing hit: 0
    local = to_camera(world)
    depth = exr["depth.Z"]
    for j in range(H):
        for i in range(W):
            if j < H // 2 and i < W // 2:
                continue
            x, y, z = local[j, i]
            # On its plane, at the pixel's depth ...
            plane_z = -NEAR_PLANE if i < W // 2 else -(4 + TILT * y)
            assert z == pytest.approx(plane_z, abs=2e-5), (i, j)
            assert -z == pytest.approx(float(depth[j, i]), rel=1e-5), (i, j)
            # ... and seen through the pixel: its ray's (a, b) lie within the pixel's edges.
            a, b = x / -z, y / -z
            (a0, b0), (a1, b1) = ray(i, j + 1), ray(i + 1, j)
            assert a0 - 1e-5 <= a <= a1 + 1e-5 and b0 - 1e-5 <= b <= b1 + 1e-5, (i, j)
    # The world positions are not the camera-space ones (the transform counts).
    assert np.abs(world - local).max() > 1


def test_a_job_without_aovs_has_none_of_their_layers(outputs):
    job, plain, exr, plain_exr, pngs, refused, _ = outputs
    assert {"depth.Z", "position.X", "position.Y", "position.Z"} <= set(exr)
    assert not any(name.startswith(("depth", "position")) for name in plain_exr)
    assert refused.status == 400 and refused.field == "layer"
    assert "without settings.aovs naming depth" in refused.message
    # The image itself does not depend on the outputs: same scene, settings and seed.
    for c in "RGBA":
        assert np.array_equal(exr[c], plain_exr[c]), c
    assert job["settings"]["aovs"] == "depth,position" and plain["settings"]["aovs"] == ""
    for layer, png in pngs.items():
        assert png.startswith(b"\x89PNG"), layer


def test_the_cli_downloads_one_output_layer(outputs, farm):
    from .test_outputs import _cli

    job, plain, exr, _, _, _, out = outputs
    target = out / "depth-only.exr"
    done = _cli(farm, "get", job["id"], "-o", str(target), "--layer", "depth")
    assert done.returncode == 0, done.stderr
    only = read_exr(str(target))
    assert set(only) == {"depth.Z"}
    assert np.array_equal(only["depth.Z"], exr["depth.Z"])
    done = _cli(farm, "get", plain["id"], "-o", str(out / "none.exr"), "--layer", "position")
    assert done.returncode == 1
    assert "no position layer (it was submitted without --aovs naming position)" in done.stderr
