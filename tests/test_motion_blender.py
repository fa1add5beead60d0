"""Blender itself as the reference for the convention of the farm's motion output (#40,
tests/test_motion_farm.py): the same animated scene (a quad moving at a known speed in front
of a still wall), imported with Blender's own glTF importer at the same fps and rendered by
Cycles at the same frame with its Vector pass (tests/blender_motion.py), must give the analytic
motion of that scene in the convention the farm's `motion` layer documents: X, Y the previous
position minus the current one, Z, W the current minus the next, in pixels, y up. No farm."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .test_aovs_blender import read_layers
from .test_blender_addon import run_blender_script
from .test_motion_farm import FPS, FRAME, H, W, inside, pixel_motion, quad_at, scene

SCRIPT = Path(__file__).with_name("blender_motion.py")


def test_blenders_vector_pass_is_the_documented_convention(tmp_path):
    gltf = tmp_path / "mover.gltf"
    gltf.write_text(json.dumps(scene()))
    args = [str(gltf), str(tmp_path / "mover.exr"), str(W), str(H), str(int(FPS)), str(FRAME)]
    channels = read_layers(Path(run_blender_script(SCRIPT, args, tmp_path)["exr"]))
    vector = np.stack([channels[f"ViewLayer.Vector.{a}"] for a in "XYZW"], -1)
    d, e = pixel_motion()  # right and down, per frame
    quad = inside(quad_at(FRAME / FPS))
    assert quad.sum() >= 20
    want = np.array([-d, e, -d, e])
    np.testing.assert_allclose(vector[quad], np.broadcast_to(want, vector[quad].shape), atol=2e-3)
    wall = ~inside(quad_at(FRAME / FPS), margin=-1.0)
    assert np.abs(vector[wall]).max() < 1e-6
