"""The `lobes` output on a real farm (#40): quads facing a pinhole camera under a uniform
environment, one material each, whose lobe radiance has an answer without rendering:

- a Lambert quad (base 0.8, KHR_materials_specular specularFactor 0: no specular layer, so its
  BRDF is base / pi) under a uniform environment of radiance E reflects 0.8 E, all of it
  `diffuse_direct` (one bounce, nothing else in view: the quads are coplanar);
- a white rough metal (base 1, metallic 1) reflects E through its GGX lobe and the
  multiple-scattering term, so its pixels' radiance is all `glossy_direct` and none diffuse;
- a black emissive quad (base 0, specularFactor 0) shows its emission and nothing else;
- where the camera sees the environment, `background` is E and nothing else;
- a smooth glass quad shows the environment through it (`transmission_direct`) and reflected
  (`glossy_direct`), nothing diffuse.

And on every pixel the eight lobe layers sum to the image (R, G, B), the property compositors
rely on when they rebuild the beauty from the passes."""

from __future__ import annotations

import base64
import json
import math

import numpy as np
import pytest

from renderfarm.client import Client
from renderfarm.domain.channels import LOBES
from renderfarm.infra.images import read_exr

from .waiting import wait_until

W, H = 48, 32
YFOV = 0.7
DEPTH = 4.0
E = 0.5  # the environment's radiance
LAMP = (2.0, 1.0, 0.5)
SPP = 64
SETTINGS = {"width": W, "height": H, "tile_size": 16, "max_spp": SPP, "noise_threshold": 0,
            "max_depth": 4, "aovs": ["lobes"]}  # fmt: skip
DATA_URI = "data:application/octet-stream;base64,"
HALF_H = DEPTH * math.tan(YFOV / 2)  # the view's half height at DEPTH
HALF_W = HALF_H * W / H
# Each quad's extent (x0, y0, x1, y1) at DEPTH, in scene units (x right, y up).
QUADS = {
    "diffuse": (-HALF_W - 1, -HALF_H - 1, -0.8, HALF_H + 1),
    "metal": (-0.7, -HALF_H - 1, 0.6, HALF_H + 1),
    "glass": (0.7, 0.1, 1.4, HALF_H + 1),
    "lamp": (1.5, 0.1, HALF_W + 1, HALF_H + 1),
}
MATERIALS = [
    {"name": "diffuse", "pbrMetallicRoughness": {"baseColorFactor": [0.8, 0.8, 0.8, 1],
                                                 "metallicFactor": 0, "roughnessFactor": 1},
     "extensions": {"KHR_materials_specular": {"specularFactor": 0}}},
    {"name": "metal", "pbrMetallicRoughness": {"baseColorFactor": [1, 1, 1, 1],
                                               "metallicFactor": 1, "roughnessFactor": 0.4}},
    {"name": "glass", "pbrMetallicRoughness": {"metallicFactor": 0, "roughnessFactor": 0},
     "extensions": {"KHR_materials_transmission": {"transmissionFactor": 1}}},
    {"name": "lamp", "emissiveFactor": list(LAMP),
     "pbrMetallicRoughness": {"baseColorFactor": [0, 0, 0, 1], "metallicFactor": 0},
     "extensions": {"KHR_materials_specular": {"specularFactor": 0}}},
]  # fmt: skip


def scene() -> dict:
    blob, views, accessors, meshes, nodes = b"", [], [], [], []
    for i, (name, (x0, y0, x1, y1)) in enumerate(QUADS.items()):
        corners = np.array([(x0, y0, 0), (x1, y0, 0), (x1, y1, 0), (x0, y1, 0)], np.float32)
        for part, kind in ((corners, "VEC3"), (np.array([0, 1, 2, 0, 2, 3], np.uint16), "SCALAR")):
            views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": part.nbytes})
            blob += part.tobytes() + b"\0" * (-part.nbytes % 4)
            accessor = {"bufferView": len(views) - 1, "count": len(part), "type": kind,
                        "componentType": 5126 if kind == "VEC3" else 5123}  # fmt: skip
            if kind == "VEC3":
                accessor |= {"min": corners.min(0).tolist(), "max": corners.max(0).tolist()}
            accessors.append(accessor)
        meshes.append({"name": name, "primitives": [
            {"attributes": {"POSITION": 2 * i}, "indices": 2 * i + 1, "material": i}]})  # fmt: skip
        nodes.append({"name": name, "mesh": i, "translation": [0, 0, -DEPTH]})
    nodes.append({"name": "camera", "camera": 0})
    return {
        "asset": {"version": "2.0"},
        "extensionsUsed": ["KHR_materials_specular", "KHR_materials_transmission"],
        "scene": 0,
        "scenes": [{"nodes": list(range(len(nodes)))}],
        "nodes": nodes,
        "cameras": [{"type": "perspective",
                     "perspective": {"yfov": YFOV, "aspectRatio": W / H, "znear": 0.05}}],
        "meshes": meshes,
        "materials": MATERIALS,
        "buffers": [{"byteLength": len(blob), "uri": DATA_URI + base64.b64encode(blob).decode()}],
        "bufferViews": views,
        "accessors": accessors,
    }  # fmt: skip


def region(x0: float, y0: float, x1: float, y1: float, margin: float = 1.0) -> np.ndarray:
    """Pixels wholly inside the rectangle (scene units at DEPTH), `margin` pixels in."""
    f = (H / 2) / HALF_H  # pixels per scene unit at DEPTH
    u0, u1 = W / 2 + f * x0, W / 2 + f * x1
    v0, v1 = H / 2 - f * y1, H / 2 - f * y0
    i, j = np.meshgrid(np.arange(W), np.arange(H))
    return (i >= u0 + margin) & (i + 1 <= u1 - margin) & (j >= v0 + margin) & (j + 1 <= v1 - margin)


def uniform_hdr(path, radiance: float) -> None:
    """An environment map of one radiance everywhere (a power of two: exact in RGBE)."""
    import OpenImageIO as oiio

    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), oiio.ImageSpec(16, 8, 3, oiio.FLOAT))
    out.write_image(np.full((8, 16, 3), radiance, dtype=np.float32))
    out.close()


@pytest.fixture(scope="module")
def lobes(farm, tmp_path_factory):
    out = tmp_path_factory.mktemp("lobes")
    path = out / "quads.gltf"
    path.write_text(json.dumps(scene()))
    uniform_hdr(out / "sky.hdr", E)
    with Client(farm.url, timeout=120) as client:
        wait_until(lambda: len(client.workers()) >= 1, 30, "a worker connected")
        job = client.submit(str(path), name="lobes",
                            settings={**SETTINGS, "environment": str(out / "sky.hdr")})  # fmt: skip
        done = client.wait(job["id"], poll_s=0.2, timeout_s=600)
        assert done["state"] == "completed", done
        client.save_image(job["id"], out / "lobes.exr", "exr")
        png = client.image(job["id"], "png", layer="glossy_direct")
    return read_exr(str(out / "lobes.exr")), png


def lobe(exr: dict, name: str) -> np.ndarray:
    return np.stack([exr[f"{name}.{c}"] for c in "RGB"], -1).astype(np.float64)


def test_the_lobes_sum_to_the_image_on_every_pixel(lobes):
    exr, png = lobes
    rgb = np.stack([exr[c] for c in "RGB"], -1).astype(np.float64)
    total = sum(lobe(exr, name) for name, *_ in LOBES)
    assert rgb.max() > 1.0  # the lamp: not vacuous
    # A worker sums a task's samples (at most 64) of each layer in float32 and the radiance in
    # float64, the server every task's sums in float64: they agree to float32 rounding.
    np.testing.assert_allclose(total, rgb, rtol=2e-5, atol=1e-6)
    assert png.startswith(b"\x89PNG")


def test_each_materials_radiance_lands_in_its_lobe(lobes):
    exr, _ = lobes
    names = [name for name, *_ in LOBES]
    layers = {name: lobe(exr, name) for name in names}
    zero_but = {  # the region, and the layers that may be nonzero there
        "diffuse": ("diffuse_direct",),
        "metal": ("glossy_direct",),
        "glass": ("glossy_direct", "transmission_direct"),
        "lamp": ("emission",),
    }
    for quad, allowed in zero_but.items():
        pixels = region(*QUADS[quad])
        assert pixels.sum() >= 8, quad
        for name in names:
            if name not in allowed:
                assert np.abs(layers[name][pixels]).max() == 0.0, (quad, name)
    # The Lambert quad reflects 0.8 E: the mean over its pixels within 4 standard errors.
    diffuse = layers["diffuse_direct"][region(*QUADS["diffuse"])]
    err = diffuse.std() / math.sqrt(diffuse.size) + 1e-4
    assert abs(diffuse.mean() - 0.8 * E) < 4 * err + 1e-3, (diffuse.mean(), err)
    # The white metal conserves energy (Kulla-Conty): E, to its table's accuracy (1%).
    metal = layers["glossy_direct"][region(*QUADS["metal"])]
    assert abs(metal.mean() - E) < 0.01 * E + 4 * metal.std() / math.sqrt(metal.size)
    # The glass shows the environment mostly through it, a little reflected (Fresnel at ior
    # 1.5 near normal incidence: 4%).
    glass = region(*QUADS["glass"])
    through, mirror = layers["transmission_direct"][glass], layers["glossy_direct"][glass]
    assert through.mean() > 10 * mirror.mean() > 0
    # The lamp shows exactly its emission.
    np.testing.assert_allclose(layers["emission"][region(*QUADS["lamp"])],
                               np.broadcast_to(LAMP, (region(*QUADS["lamp"]).sum(), 3)),
                               rtol=1e-6)  # fmt: skip
    # Where nothing is in view: the environment, exactly, as `background` only.
    sky = region(0.7, -HALF_H - 1, HALF_W + 1, 0.0)
    assert sky.sum() >= 8
    np.testing.assert_allclose(layers["background"][sky], E, rtol=1e-6)
    for name in names:
        if name != "background":
            assert np.abs(layers[name][sky]).max() == 0.0, name
