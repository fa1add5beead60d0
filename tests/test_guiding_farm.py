"""Path guiding on a real farm (the job setting `guiding`, #38): a Lambert floor seen from above
that is lit almost only indirectly, by the underside of a white square that a small emitter
facing up lights from below (the floor sees the emitter's dark back), plus a thin emitter off
to the side that lights the floor directly. The floor's BSDF finds the square with the
probability of its form factor; the guide learns its direction. What the farm must show needs
no renderer of its own:

- the same guided job twice gives the same bits, although the farm's two workers split its
  tiles between them differently each time (each trains the same field);
- guided and unguided images converge to the same mean: their difference over the image is
  within its standard error (estimated from the spread of two seeds of each);
- the guided image is less noisy: two seeds of it differ less than two seeds without it."""

from __future__ import annotations

import base64
import json

import numpy as np
import pytest

from renderfarm.client import Client
from renderfarm.infra.images import read_exr

from .waiting import wait_until

W, H = 48, 32
SETTINGS = {"width": W, "height": H, "tile_size": 16, "max_spp": 64, "noise_threshold": 0,
            "max_depth": 3, "sampler": "independent"}  # fmt: skip
DATA_URI = "data:application/octet-stream;base64,"


def quad(y: float, half: float, up: bool, x0: float = 0.0) -> np.ndarray:
    """A square of side 2 * half at height y centred on (x0, z = 0), facing +y (up) or -y: its
    corners in the order that makes that face counter-clockwise (the front)."""
    corners = [(-half, -half), (-half, half), (half, half), (half, -half)]
    if not up:
        corners.reverse()
    return np.array([(x0 + x, y, z) for x, z in corners], np.float32)


def scene() -> dict:
    parts = [
        quad(0.0, 20.0, True),  # the floor
        quad(1.0, 0.3, False),  # the white square, facing down
        quad(0.6, 0.05, True),  # the emitter under it, facing up
        quad(2.0, 0.02, False, x0=1.5),  # the direct emitter, facing down
    ]
    indices = np.array([0, 1, 2, 0, 2, 3], np.uint16)
    blob, views = b"", []
    for part in (*parts, indices):
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": part.nbytes})
        blob += part.tobytes() + b"\0" * (-part.nbytes % 4)
    accessors = [{"bufferView": k, "componentType": 5126, "count": 4, "type": "VEC3",
                  "min": part.min(0).tolist(), "max": part.max(0).tolist()}
                 for k, part in enumerate(parts)]  # fmt: skip
    accessors.append({"bufferView": len(parts), "componentType": 5123, "count": 6,
                      "type": "SCALAR"})  # fmt: skip
    materials = [(0.8, 0.0), (0.9, 0.0), (0.0, 50.0)]  # (albedo, emission)
    meshes = [0, 1, 2, 2]  # each part's material
    return {
        "asset": {"version": "2.0"},
        "extensionsUsed": ["KHR_materials_emissive_strength", "KHR_materials_specular"],
        "scene": 0,
        "scenes": [{"nodes": list(range(len(parts) + 1))}],
        # The camera 0.4 above the floor, looking straight down (-90 degrees about x).
        "nodes": [{"mesh": k} for k in range(len(parts))] + [
            {"camera": 0, "translation": [0, 0.4, 0], "rotation": [-0.7071068, 0, 0, 0.7071068]}],
        "cameras": [{"type": "perspective",
                     "perspective": {"yfov": 1.0, "aspectRatio": W / H, "znear": 0.01}}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": k}, "indices": len(parts),
                                    "material": m}]} for k, m in enumerate(meshes)],
        "materials": [
            {"pbrMetallicRoughness": {"baseColorFactor": [a, a, a, 1], "metallicFactor": 0},
             "emissiveFactor": [1, 1, 1] if e else [0, 0, 0],
             "extensions": {"KHR_materials_specular": {"specularFactor": 0},
                            **({"KHR_materials_emissive_strength": {"emissiveStrength": e}}
                               if e else {})}}
            for a, e in materials],
        "buffers": [{"byteLength": len(blob), "uri": DATA_URI + base64.b64encode(blob).decode()}],
        "bufferViews": views,
        "accessors": accessors,
    }  # fmt: skip


def luminance(exr: dict) -> np.ndarray:
    return 0.2126 * exr["R"] + 0.7152 * exr["G"] + 0.0722 * exr["B"]


@pytest.fixture(scope="module")
def renders(farm, tmp_path_factory):
    out = tmp_path_factory.mktemp("guiding")
    path = out / "patch.gltf"
    path.write_text(json.dumps(scene()))
    images = {}
    with Client(farm.url, timeout=120) as client:
        wait_until(lambda: len(client.workers()) >= 2, 30, "both workers connected")
        jobs = {
            "guided": {"guiding": True, "seed": 7},
            "guided_again": {"guiding": True, "seed": 7},
            "guided_seed8": {"guiding": True, "seed": 8},
            "plain": {"guiding": False, "seed": 7},
            "plain_seed8": {"guiding": False, "seed": 8},
        }
        for name, extra in jobs.items():
            job = client.submit(str(path), name=name, settings={**SETTINGS, **extra})
            done = client.wait(job["id"], poll_s=0.2, timeout_s=600)
            assert done["state"] == "completed", done
            assert done["settings"]["guiding"] is extra["guiding"]
            client.save_image(job["id"], out / f"{name}.exr", "exr")
            images[name] = read_exr(str(out / f"{name}.exr"))
    return images


def test_the_same_guided_job_gives_the_same_bits(renders):
    for c in "RGB":
        assert np.array_equal(renders["guided"][c], renders["guided_again"][c])
    # And guiding changed the image: the field was used.
    assert not np.array_equal(renders["guided"]["R"], renders["plain"]["R"])


def test_guided_and_unguided_converge_to_the_same_mean_with_less_noise(renders):
    g, g8 = luminance(renders["guided"]), luminance(renders["guided_seed8"])
    p, p8 = luminance(renders["plain"]), luminance(renders["plain_seed8"])
    # Per pixel, the variance of one render: half that of the difference of two seeds.
    var_g = np.var(g - g8) / 2
    var_p = np.var(p - p8) / 2
    assert p.mean() > 0
    se = np.sqrt((var_g + var_p) / g.size)
    assert abs(g.mean() - p.mean()) < 4 * se, (g.mean(), p.mean(), se)
    assert var_g < 0.7 * var_p, (var_g, var_p)
