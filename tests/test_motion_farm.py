"""The motion output on a real farm (#40): a quad moving at a known speed in front of a still
wall, seen by a still pinhole camera. Between frames (1 / fps apart) the quad moves a known
distance, so its pixels move FOCAL x distance / depth pixels; the expected values are that
arithmetic in Blender's Vector-pass convention (X, Y: previous minus current; Z, W: current
minus next; y up), the wall's pixels do not move, and a still has no motion."""

from __future__ import annotations

import base64
import json
import math

import numpy as np
import pytest

from renderfarm.client import Client
from renderfarm.infra.images import read_exr

from .waiting import wait_until

W, H = 48, 32
YFOV = 0.7
F = (H / 2) / math.tan(YFOV / 2)  # focal length in pixels
FPS = 24.0
FRAME = 12  # glTF time 0.5 s
DEPTH = 4.0  # the quad's distance
VELOCITY = (2.4, -1.2)  # the quad's world velocity, units per second (x right, y up)
SETTINGS = {"width": W, "height": H, "tile_size": 16, "max_spp": 2, "noise_threshold": 0,
            "aovs": ["motion"]}  # fmt: skip
DATA_URI = "data:application/octet-stream;base64,"


def pixel_motion() -> tuple[float, float]:
    """The quad's motion per frame in image pixels (x right, y down)."""
    return F * VELOCITY[0] / FPS / DEPTH, -F * VELOCITY[1] / FPS / DEPTH


def quad_at(time_s: float) -> tuple[float, float, float, float]:
    """The quad's pixel rectangle (u0, v0, u1, v1) at a time: its corners (-0.6, -0.4) and
    (0.6, 0.4) (node space) moved by the velocity, at DEPTH."""
    x = VELOCITY[0] * time_s
    y = VELOCITY[1] * time_s
    return (W / 2 + F * (x - 0.6) / DEPTH, H / 2 - F * (y + 0.4) / DEPTH,
            W / 2 + F * (x + 0.6) / DEPTH, H / 2 - F * (y - 0.4) / DEPTH)  # fmt: skip


def scene() -> dict:
    quad = np.array([(-0.6, -0.4, 0), (0.6, -0.4, 0), (0.6, 0.4, 0), (-0.6, 0.4, 0)], np.float32)
    wall = np.array([(-9, -9, 0), (9, -9, 0), (9, 9, 0), (-9, 9, 0)], np.float32)
    indices = np.array([0, 1, 2, 0, 2, 3], np.uint16)
    times = np.array([0.0, 2.0], np.float32)
    moves = np.array([(0, 0, -DEPTH), (2 * VELOCITY[0], 2 * VELOCITY[1], -DEPTH)], np.float32)
    parts = [quad, wall, indices, times, moves]
    blob, views = b"", []
    for part in parts:
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": part.nbytes})
        blob += part.tobytes() + b"\0" * (-part.nbytes % 4)
    return {
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0, 1, 2]}],
        "nodes": [
            {"name": "camera", "camera": 0},
            {"name": "mover", "mesh": 0, "translation": [0, 0, -DEPTH]},
            {"name": "wall", "mesh": 1, "translation": [0, 0, -8]},
        ],
        "cameras": [{"type": "perspective",
                     "perspective": {"yfov": YFOV, "aspectRatio": W / H, "znear": 0.05}}],
        "meshes": [
            {"name": "quad", "primitives": [{"attributes": {"POSITION": 0}, "indices": 2,
                                             "material": 0}]},
            {"name": "wall", "primitives": [{"attributes": {"POSITION": 1}, "indices": 2,
                                             "material": 0}]},
        ],
        "materials": [{"name": "glow", "emissiveFactor": [1, 1, 1], "doubleSided": True}],
        "animations": [{
            "channels": [{"sampler": 0, "target": {"node": 1, "path": "translation"}}],
            "samplers": [{"input": 3, "output": 4, "interpolation": "LINEAR"}],
        }],
        "buffers": [{"byteLength": len(blob), "uri": DATA_URI + base64.b64encode(blob).decode()}],
        "bufferViews": views,
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3",
             "min": [-0.6, -0.4, 0], "max": [0.6, 0.4, 0]},
            {"bufferView": 1, "componentType": 5126, "count": 4, "type": "VEC3",
             "min": [-9, -9, 0], "max": [9, 9, 0]},
            {"bufferView": 2, "componentType": 5123, "count": 6, "type": "SCALAR"},
            {"bufferView": 3, "componentType": 5126, "count": 2, "type": "SCALAR",
             "min": [0.0], "max": [2.0]},
            {"bufferView": 4, "componentType": 5126, "count": 2, "type": "VEC3"},
        ],
    }  # fmt: skip


def inside(rect: tuple[float, float, float, float], margin: float = 1.0) -> np.ndarray:
    """Pixels wholly inside a pixel rectangle, `margin` pixels from its edges."""
    u0, v0, u1, v1 = rect
    i, j = np.meshgrid(np.arange(W), np.arange(H))
    return (i >= u0 + margin) & (i + 1 <= u1 - margin) & (j >= v0 + margin) & (j + 1 <= v1 - margin)


@pytest.fixture(scope="module")
def motion(farm, tmp_path_factory):
    out = tmp_path_factory.mktemp("motion")
    path = out / "mover.gltf"
    path.write_text(json.dumps(scene()))
    with Client(farm.url, timeout=120) as client:
        wait_until(lambda: len(client.workers()) >= 1, 30, "a worker connected")
        animated = client.submit(
            str(path), name="motion", settings={**SETTINGS, "frames": str(FRAME), "fps": FPS}
        )
        still = client.submit(str(path), settings=SETTINGS, name="motion still")
        for job in (animated, still):
            done = client.wait(job["id"], poll_s=0.2, timeout_s=600)
            assert done["state"] == "completed", done
        (out / "frame.exr").write_bytes(client.frame_image(animated["id"], FRAME, "exr"))
        client.save_image(still["id"], out / "still.exr", "exr")
        png = client.frame_image(animated["id"], FRAME, "png", layer="motion")
    return read_exr(str(out / "frame.exr")), read_exr(str(out / "still.exr")), png


def test_a_moving_quads_pixels_move_by_its_speed_in_blenders_convention(motion):
    frame, _, png = motion
    vector = np.stack([frame[f"motion.{a}"] for a in "XYZW"], -1).astype(np.float64)
    d, e = pixel_motion()  # right and down, per frame
    assert abs(d) > 1 and abs(e) > 0.5  # not vacuous: more than a pixel across
    quad = inside(quad_at(FRAME / FPS))
    assert quad.sum() >= 20
    want = np.array([-d, e, -d, e])  # X, Y: previous - current; Z, W: current - next; y up
    np.testing.assert_allclose(vector[quad], np.broadcast_to(want, vector[quad].shape), atol=2e-3)
    # The wall does not move: wherever the quad is not (now), 0.
    wall = ~inside(quad_at(FRAME / FPS), margin=-1.0)
    assert wall.sum() > W * H // 2
    assert np.abs(vector[wall]).max() < 1e-6
    assert png.startswith(b"\x89PNG")


def test_a_still_has_no_motion(motion):
    _, still, _ = motion
    for a in "XYZW":
        assert (still[f"motion.{a}"] == 0).all(), a
