"""A product-shot scene for the adaptive-sampling benchmark: a box on a floor under a sky.

Half the frame is sky (the environment map seen directly: converged after a few samples); the
floor holds soft shadows and indirect light (slow to converge). That split between easy and hard
regions is where stopping tiles on their own error pays (bench/adaptive_efficiency.py), unlike
a closed interior such as the Cornell box, where every tile needs many samples.

write(dir) writes sky-box.gltf (buffer embedded) and sky.hdr (an equirectangular sky with a sun)
and returns their paths.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from . import quad_mesh

# Axis-aligned box [x0, x1] x [0, h] x [z0, z1] and a large floor at y = 0.
BOX = (-0.5, 0.5, 1.0, -0.5, 0.5)
FLOOR = 30.0


def _quads() -> tuple[list[tuple], list[tuple]]:
    """(floor quads, box quads), each quad four corners counter-clockwise seen from outside."""
    x0, x1, h, z0, z1 = BOX
    floor = [((-FLOOR, 0, FLOOR), (FLOOR, 0, FLOOR), (FLOOR, 0, -FLOOR), (-FLOOR, 0, -FLOOR))]
    box = [
        ((x0, h, z1), (x1, h, z1), (x1, h, z0), (x0, h, z0)),  # top, +y
        ((x0, 0, z1), (x1, 0, z1), (x1, h, z1), (x0, h, z1)),  # front, +z
        ((x1, 0, z0), (x0, 0, z0), (x0, h, z0), (x1, h, z0)),  # back, -z
        ((x1, 0, z1), (x1, 0, z0), (x1, h, z0), (x1, h, z1)),  # right, +x
        ((x0, 0, z0), (x0, 0, z1), (x0, h, z1), (x0, h, z0)),  # left, -x
    ]
    return floor, box


def gltf() -> dict:
    floor, box = _quads()
    parts = quad_mesh.meshes([("floor", floor, 0), ("box", box, 1)])
    # Camera at (0, 1.1, 4.5) looking slightly down (pitch -3 degrees about x).
    pitch = math.radians(-3.0)
    rotation = [math.sin(pitch / 2), 0.0, 0.0, math.cos(pitch / 2)]
    return {
        "asset": {"version": "2.0", "generator": "renderfarm bench/support/sky_scene.py"},
        "scene": 0,
        "scenes": [{"nodes": [0, 1, 2]}],
        "nodes": [
            {"name": "floor", "mesh": 0},
            {"name": "box", "mesh": 1, "rotation": [0.0, math.sin(0.3), 0.0, math.cos(0.3)]},
            {
                "name": "camera",
                "camera": 0,
                "translation": [0.0, 1.1, 4.5],
                "rotation": rotation,
            },  # fmt: skip
        ],
        "cameras": [
            {
                "type": "perspective",
                "perspective": {"yfov": 0.75, "aspectRatio": 1.0, "znear": 0.01},
            }
        ],  # fmt: skip
        "materials": [
            quad_mesh.diffuse("floor", (0.5, 0.5, 0.5)),
            quad_mesh.diffuse("box", (0.8, 0.35, 0.1), roughness=0.5),
        ],
        **parts,
    }


def sky(width: int = 128, height: int = 64) -> np.ndarray:
    """Equirectangular sky radiance (rows from the zenith down): a blue gradient above the
    horizon, a dim ground below it, and a small bright sun 35 degrees above the horizon."""
    theta = (np.arange(height) + 0.5) / height * np.pi  # polar angle from +y
    phi = (np.arange(width) + 0.5) / width * 2 * np.pi
    t, p = np.meshgrid(theta, phi, indexing="ij")
    up = np.cos(t)
    img = np.where(up[..., None] > 0,
                   np.stack([0.35 + 0.3 * (1 - up), 0.55 + 0.25 * (1 - up), np.full_like(up, 1.0)],
                            axis=-1),
                   np.array([0.15, 0.13, 0.1]))  # fmt: skip
    sun_dir = np.array([math.cos(math.radians(35)) * math.cos(1.0), math.sin(math.radians(35)),
                        math.cos(math.radians(35)) * math.sin(1.0)])  # fmt: skip
    d = np.stack([np.sin(t) * np.cos(p), np.cos(t), np.sin(t) * np.sin(p)], axis=-1)
    sun = (d @ sun_dir) > math.cos(math.radians(4.0))
    img[sun] = [400.0, 380.0, 340.0]
    return img.astype(np.float32)


def write(directory: Path) -> tuple[Path, Path]:
    import OpenImageIO as oiio

    directory.mkdir(parents=True, exist_ok=True)
    scene = directory / "sky-box.gltf"
    scene.write_text(json.dumps(gltf()))
    env = directory / "sky.hdr"
    pixels = sky()
    out = oiio.ImageOutput.create(str(env))
    out.open(str(env), oiio.ImageSpec(pixels.shape[1], pixels.shape[0], 3, oiio.FLOAT))
    out.write_image(pixels)
    out.close()
    return scene, env
