"""Blender itself as the reference for the conventions of the farm's depth and position outputs
(#40, tests/test_aovs_farm.py): the same scene (a plane facing the camera bottom left, nothing top
left, a plane tilted about the camera's horizontal axis right), imported with Blender's own glTF
importer and rendered by Cycles with its Depth and Position passes (tests/blender_aovs.py), must
give the analytic values of that scene's pinhole geometry. Depth is the distance along the
viewing axis (planar: one value over the facing plane, not the longer ray lengths to its
corners) and 1e10 where nothing is hit; Position is the world-space point of the first hit in
Blender's Z-up world, which the importer's axes (glTF (x, y, z) is Blender (x, -z, y)) take back
to glTF's as (x, z, -y), and 0 where nothing is hit. No farm: nothing here asks for `farm`."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from .test_aovs_farm import CAMERA_AT, NEAR_PLANE, TILT, H, W, ray, scene, to_camera
from .test_blender_addon import run_blender_script

SCRIPT = Path(__file__).with_name("blender_aovs.py")
CHANNELS = {"ViewLayer.Depth.Z", "ViewLayer.Position.X", "ViewLayer.Position.Y",
            "ViewLayer.Position.Z"}  # fmt: skip


def read_layers(path: Path) -> dict[str, np.ndarray]:
    """Every channel of a multi-part EXR by name: Blender 5.0 writes each pass of a multilayer
    EXR as its own part (subimage), and renderfarm.infra.images.read_exr reads only the first."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    assert inp is not None, oiio.geterror()
    channels: dict[str, np.ndarray] = {}
    try:
        part = 0
        while inp.seek_subimage(part, 0):
            spec = inp.spec()
            pixels = inp.read_image(part, 0, 0, spec.nchannels, oiio.FLOAT)
            channels.update({name: pixels[..., i] for i, name in enumerate(spec.channelnames)})
            part += 1
    finally:
        inp.close()
    return channels


@pytest.fixture(scope="module")
def blender(tmp_path_factory) -> dict[str, np.ndarray]:
    out = tmp_path_factory.mktemp("aovs-blender")
    gltf = out / "planes.gltf"
    gltf.write_text(json.dumps(scene()))
    result = run_blender_script(SCRIPT, [str(gltf), str(out / "planes.exr")], out)
    channels = read_layers(Path(result["exr"]))
    assert CHANNELS <= set(channels), sorted(channels)
    return channels


def gltf_position(blender: dict[str, np.ndarray]) -> np.ndarray:
    """Blender's Position (Z up) in glTF's axes (Y up): (x, z, -y)."""
    x, y, z = (blender[f"ViewLayer.Position.{a}"].astype(np.float64) for a in "XYZ")
    return np.stack([x, z, -y], -1)


def test_blenders_depth_is_along_the_viewing_axis_and_1e10_on_background(blender):
    depth = blender["ViewLayer.Depth.Z"]
    assert depth.shape == (H, W)
    # Bottom left: the facing plane, one depth over it all.
    np.testing.assert_allclose(depth[H // 2 :, : W // 2], NEAR_PLANE, rtol=1e-5)
    # Top left: nothing hit.
    assert (depth[: H // 2, : W // 2] == 1e10).all()
    # Right half: the tilted plane, each pixel's depth between the values at its edges.
    for j in range(H):
        for i in range(W // 2, W):
            edges = [4 / (1 - TILT * ray(i, y)[1]) for y in (j, j + 1)]
            assert min(edges) * (1 - 1e-5) <= depth[j, i] <= max(edges) * (1 + 1e-5), (i, j)


def test_blenders_depth_is_not_the_ray_length(blender):
    """Planar, not radial: at the corner pixels (the three that see a plane) the ray is over 15%
    longer than the depth, by the analytic geometry and by Blender's own hit point."""
    depth = blender["ViewLayer.Depth.Z"]
    world = gltf_position(blender)
    for i, j in ((0, H - 1), (W - 1, 0), (W - 1, H - 1)):
        # The ray's length per unit of depth, between its values at the pixel's corners.
        stretch = [math.hypot(1, *ray(x, y)) for x in (i, i + 1) for y in (j, j + 1)]
        assert min(stretch) > 1.15, (i, j)
        ray_length = float(np.linalg.norm(world[j, i] - CAMERA_AT))
        assert ray_length > 1.15 * depth[j, i], (i, j)
        lo, hi = min(stretch) * (1 - 1e-5), max(stretch) * (1 + 1e-5)
        assert lo <= ray_length / depth[j, i] <= hi, (i, j)
    assert depth[H - 1, 0] == pytest.approx(NEAR_PLANE, rel=1e-5)


def test_blenders_position_in_gltf_axes_is_the_first_hit_and_0_on_background(blender):
    raw = np.stack([blender[f"ViewLayer.Position.{a}"] for a in "XYZ"], -1)
    assert (raw[: H // 2, : W // 2] == 0).all()  # nothing hit: 0
    world = gltf_position(blender)
    local = to_camera(world)
    depth = blender["ViewLayer.Depth.Z"]
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
    # The world positions are not the camera-space ones (the transform counts), and the axes'
    # change is not the identity here (Blender's y and z differ).
    assert np.abs(world - local).max() > 1
    assert np.abs(world - raw).max() > 1
