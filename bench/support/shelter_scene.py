"""A scene with a bright, easy region and a dark, hard one, for the adaptive-sampling benchmark.

A white ground in full sun, and a shelter (roof, back and side walls, open towards the camera)
whose inside and the strip of ground in its shadow are lit only by sunlight bounced off the
ground: dim, and noisy, since that light arrives through several diffuse bounces. The sunlit
ground converges in a few samples (its direct light comes from one deterministic shadow ray per
sample). Unlike a sky seen directly, the easy region is not free: its paths bounce like any
other, so samples adaptive stopping saves there pay for the hard region.

write(dir) writes shelter.gltf (buffer embedded) and returns its path.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from . import quad_mesh

GROUND = 40.0
# The shelter: x in [-W, W], y in [0, H], z in [-D, 0]; open at z = 0 (towards the camera).
W, H, D = 1.4, 1.1, 1.6
SUN_ELEVATION_DEG = 55.0  # the sun shines from behind the shelter (-z), over its roof
SUN_IRRADIANCE = 4.0


def _quads() -> tuple[list[tuple], list[tuple]]:
    g = GROUND
    ground = [((-g, 0, g), (g, 0, g), (g, 0, -g), (-g, 0, -g))]
    shelter = [
        ((-W, H, 0), (W, H, 0), (W, H, -D), (-W, H, -D)),  # roof, facing up
        ((-W, H, 0), (-W, H, -D), (W, H, -D), (W, H, 0)),  # its underside, facing down
        ((W, 0, -D), (-W, 0, -D), (-W, H, -D), (W, H, -D)),  # back wall, facing -z
        ((-W, 0, -D), (W, 0, -D), (W, H, -D), (-W, H, -D)),  # its inside, facing +z
        ((W, 0, 0), (W, 0, -D), (W, H, -D), (W, H, 0)),  # right wall, outside (+x)
        ((W, 0, -D), (W, 0, 0), (W, H, 0), (W, H, -D)),  # its inside (-x)
        ((-W, 0, -D), (-W, 0, 0), (-W, H, 0), (-W, H, -D)),  # left wall, outside (-x)
        ((-W, 0, 0), (-W, 0, -D), (-W, H, -D), (-W, H, 0)),  # its inside (+x)
    ]
    return ground, shelter


def _about_x(angle: float) -> list[float]:
    return [math.sin(angle / 2), 0.0, 0.0, math.cos(angle / 2)]


def gltf() -> dict:
    ground, shelter = _quads()
    parts = quad_mesh.meshes([("ground", ground, 0), ("shelter", shelter, 1)])
    # A directional light shines along its node's -z: turned by pi + elevation about x, it
    # travels towards +z and down.
    sun = _about_x(math.pi + math.radians(SUN_ELEVATION_DEG))
    return {
        "asset": {"version": "2.0", "generator": "renderfarm bench/support/shelter_scene.py"},
        "extensionsUsed": ["KHR_lights_punctual"],
        "extensions": {
            "KHR_lights_punctual": {
                "lights": [{"type": "directional", "intensity": SUN_IRRADIANCE}]
            }
        },
        "scene": 0,
        "scenes": [{"nodes": [0, 1, 2, 3]}],
        "nodes": [
            {"name": "ground", "mesh": 0},
            {"name": "shelter", "mesh": 1},
            {
                "name": "sun",
                "rotation": sun,
                "extensions": {"KHR_lights_punctual": {"light": 0}},
            },  # fmt: skip
            # The camera looks down at the shelter's opening from the front.
            {
                "name": "camera",
                "camera": 0,
                "translation": [0.6, 2.4, 5.2],
                "rotation": _about_x(math.radians(-24.0)),
            },  # fmt: skip
        ],
        "cameras": [
            {
                "type": "perspective",
                "perspective": {"yfov": 0.7, "aspectRatio": 1.0, "znear": 0.01},
            }  # fmt: skip
        ],
        "materials": [
            quad_mesh.diffuse("ground", (0.75, 0.75, 0.72)),
            quad_mesh.diffuse("shelter", (0.7, 0.6, 0.5)),
        ],
        **parts,
    }


def write(directory: Path) -> Path:
    directory.mkdir(parents=True, exist_ok=True)
    scene = directory / "shelter.gltf"
    scene.write_text(json.dumps(gltf()))
    return scene
