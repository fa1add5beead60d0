"""Cryptomatte on a real farm, read back by numpy and by Blender's compositor (#40).

A camera looks down -Z at shapes drawn in pixel coordinates (so their coverage of each pixel is
plane geometry): a triangle "body" whose long edge crosses the image diagonally and a rectangle
"wheel" in front of it, both children of the root node "car", and a rectangle "lamp" of its own.
Body and lamp have the material "paint", the wheel "rubber". The expected coverage of a pixel by
a node is the area of the pixel inside the node's visible polygon (the body minus the wheel),
computed here by polygon clipping; the farm's coverage is the share of 64 samples whose first
hit was the node, so it must be within the binomial noise of 64 samples of it. Blender 5.0.1's
Cryptomatte node (tests/blender_cryptomatte.py) then opens the farm's EXR, finds the names
through its own decoding and must extract the same mattes."""

from __future__ import annotations

import base64
import json
import math
from pathlib import Path

import numpy as np
import pytest

from renderfarm.client import ApiError, Client
from renderfarm.infra.images import read_exr

from .mattes import id_hex, matte
from .test_blender_addon import run_blender_script
from .waiting import wait_until

W, H = 48, 32
SPP = 64
YFOV = 0.7
F = (H / 2) / math.tan(YFOV / 2)  # focal length in pixels
SETTINGS = {"width": W, "height": H, "tile_size": 16, "max_spp": SPP, "noise_threshold": 0,
            "aovs": ["cryptomatte"]}  # fmt: skip
# Shapes in pixel coordinates (u right, v down), and the depth of their plane.
BODY = [(-4.0, 36.0), (52.0, 36.0), (52.0, -4.0)]  # below the diagonal
WHEEL = [(6.5, 18.3), (20.25, 18.3), (20.25, 29.7), (6.5, 29.7)]  # straddles it, in front
LAMP = [(3.3, 2.4), (14.6, 2.4), (14.6, 9.7), (3.3, 9.7)]  # above it
DEPTHS = {"body": 3.0, "wheel": 2.0, "lamp": 3.0}
DATA_URI = "data:application/octet-stream;base64,"
SCRIPT = Path(__file__).with_name("blender_cryptomatte.py")


# ------------------------------------------------------------------------- plane geometry
def clip(polygon: list, a: tuple, b: tuple) -> list:
    """Sutherland-Hodgman: the part of a convex polygon left of the directed line a -> b."""

    def side(p):
        return (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0])

    out = []
    for i, p in enumerate(polygon):
        q = polygon[(i + 1) % len(polygon)]
        sp, sq = side(p), side(q)
        if sp >= 0:
            out.append(p)
        if (sp >= 0) != (sq >= 0):
            t = sp / (sp - sq)
            out.append((p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1])))
    return out


def intersect(p: list, q: list) -> list:
    """The intersection of convex polygons p and q (q counter-clockwise in u, v)."""
    for i, a in enumerate(q):
        p = clip(p, a, q[(i + 1) % len(q)])
        if not p:
            return []
    return p


def shoelace(p: list) -> float:
    """Twice the signed area of a polygon."""
    return sum(a[0] * b[1] - b[0] * a[1] for a, b in zip(p, p[1:] + p[:1], strict=True))


def area(p: list) -> float:
    return abs(shoelace(p)) / 2 if p else 0.0


def ccw(p: list) -> list:
    """p in the orientation `clip` keeps the inside of (positive shoelace sum in u, v)."""
    return p if shoelace(p) > 0 else p[::-1]


def exact_coverage() -> dict[str, np.ndarray]:
    """Per pixel, the area of it each node covers as the camera sees it (the wheel occludes
    the body)."""
    out = {n: np.zeros((H, W)) for n in ("body", "wheel", "lamp")}
    body, wheel, lamp = ccw(BODY), ccw(WHEEL), ccw(LAMP)
    for j in range(H):
        for i in range(W):
            pixel = ccw([(i, j), (i + 1, j), (i + 1, j + 1), (i, j + 1)])
            in_body = intersect(pixel, body)
            out["body"][j, i] = area(in_body) - area(intersect(in_body, wheel))
            out["wheel"][j, i] = area(intersect(pixel, wheel))
            out["lamp"][j, i] = area(intersect(pixel, lamp))
    return out


# --------------------------------------------------------------------------------- scene
def camera_space(u: float, v: float, depth: float) -> list[float]:
    return [(u - W / 2) * depth / F, (H / 2 - v) * depth / F, -depth]


def scene() -> dict:
    blob = b""
    views, accessors, meshes = [], [], []
    for name, shape in (("body", BODY), ("wheel", WHEEL), ("lamp", LAMP)):
        points = np.array([camera_space(u, v, DEPTHS[name]) for u, v in shape], np.float32)
        indices = np.array([0, 1, 2] if len(shape) == 3 else [0, 1, 2, 0, 2, 3], np.uint16)
        for data, target in ((points, 34962), (indices, 34963)):
            views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": data.nbytes,
                          "target": target})  # fmt: skip
            blob += data.tobytes() + b"\0" * (-data.nbytes % 4)
        accessors.append({"bufferView": len(views) - 2, "componentType": 5126, "type": "VEC3",
                          "count": len(points), "min": points.min(0).tolist(),
                          "max": points.max(0).tolist()})  # fmt: skip
        accessors.append({"bufferView": len(views) - 1, "componentType": 5123,
                          "type": "SCALAR", "count": len(indices)})  # fmt: skip
        material = 1 if name == "wheel" else 0
        meshes.append({"name": name, "primitives": [{
            "attributes": {"POSITION": len(accessors) - 2}, "indices": len(accessors) - 1,
            "material": material}]})  # fmt: skip
    return {
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0, 1, 4]}],
        "nodes": [
            {"name": "camera", "camera": 0},
            {"name": "car", "children": [2, 3]},
            {"name": "body", "mesh": 0},
            {"name": "wheel", "mesh": 1},
            {"name": "lamp", "mesh": 2},
        ],
        "cameras": [{"type": "perspective",
                     "perspective": {"yfov": YFOV, "aspectRatio": W / H, "znear": 0.05}}],
        "meshes": meshes,
        "materials": [
            {"name": "paint", "emissiveFactor": [1, 0.5, 0.2], "doubleSided": True},
            {"name": "rubber", "emissiveFactor": [0.1, 0.1, 0.1], "doubleSided": True},
        ],
        "buffers": [{"byteLength": len(blob), "uri": DATA_URI + base64.b64encode(blob).decode()}],
        "bufferViews": views,
        "accessors": accessors,
    }  # fmt: skip


def within_noise(got: np.ndarray, exact: np.ndarray, what: str) -> None:
    """The farm's coverage against the exact one: within 4 binomial standard errors of SPP
    samples per pixel (and one sample's worth), and unbiased over the edge pixels."""
    tolerance = 4 * np.sqrt(exact * (1 - exact) / SPP) + 1.0 / SPP
    bad = np.argwhere(np.abs(got - exact) > tolerance)
    assert not len(bad), (what, [(int(j), int(i), float(got[j, i]), float(exact[j, i]))
                                 for j, i in bad[:5]])  # fmt: skip
    edge = (exact > 0) & (exact < 1)
    assert edge.sum() > 20, what  # not vacuous: many pixels are partly covered
    bias = float((got - exact)[edge].mean())
    assert abs(bias) < 4 * 0.5 / math.sqrt(SPP * edge.sum()), (what, bias)


@pytest.fixture(scope="module")
def rendered(farm, tmp_path_factory):
    out = tmp_path_factory.mktemp("cryptomatte")
    path = out / "car.gltf"
    path.write_text(json.dumps(scene()))
    with Client(farm.url, timeout=120) as client:
        wait_until(lambda: len(client.workers()) >= 1, 30, "a worker connected")
        job = client.submit(str(path), settings=SETTINGS, name="cryptomatte")
        done = client.wait(job["id"], poll_s=0.2, timeout_s=600)
        assert done["state"] == "completed", done
        client.save_image(job["id"], out / "car.exr", "exr")
        pick = {
            what: client.pixel_mattes(job["id"], x, y)
            for what, (x, y) in {"wheel": (12, 24), "lamp": (8, 5), "nothing": (40, 2)}.items()
        }
        png = client.image(job["id"], "png", layer="crypto_asset")
        with pytest.raises(ApiError) as outside:
            client.pixel_mattes(job["id"], W, 0)
    return job, read_exr(str(out / "car.exr")), out, pick, png, outside.value


def test_coverage_of_each_node_is_the_area_it_covers(rendered):
    _, exr, _, _, _, _ = rendered
    exact = exact_coverage()
    for name in ("body", "wheel", "lamp"):
        within_noise(matte(exr, "CryptoObject", name), exact[name], name)
    # The nodes' coverages add up to the alpha (each pixel has at most three nodes).
    total = sum(matte(exr, "CryptoObject", n) for n in ("body", "wheel", "lamp"))
    np.testing.assert_allclose(total, exr["A"], atol=1e-6)


def test_assets_and_materials_group_the_nodes(rendered):
    _, exr, _, _, _, _ = rendered
    exact = exact_coverage()
    within_noise(matte(exr, "CryptoAsset", "car"), exact["body"] + exact["wheel"], "car")
    within_noise(matte(exr, "CryptoAsset", "lamp"), exact["lamp"], "lamp asset")
    within_noise(matte(exr, "CryptoMaterial", "paint"), exact["body"] + exact["lamp"], "paint")
    within_noise(matte(exr, "CryptoMaterial", "rubber"), exact["wheel"], "rubber")
    # The body's asset is the sum of its node's and the wheel's, sample for sample.
    np.testing.assert_allclose(
        matte(exr, "CryptoAsset", "car"),
        matte(exr, "CryptoObject", "body") + matte(exr, "CryptoObject", "wheel"), atol=1e-6,
    )  # fmt: skip


def test_the_header_names_the_types_and_their_manifests(rendered):
    import mmh3
    import OpenImageIO as oiio

    _, _, out, _, _, _ = rendered
    spec = oiio.ImageInput.open(str(out / "car.exr")).spec()
    for type_name, names in (("CryptoObject", {"camera", "car", "body", "wheel", "lamp"}),
                             ("CryptoMaterial", {"paint", "rubber", "default material"}),
                             ("CryptoAsset", {"camera", "car", "lamp"})):  # fmt: skip
        # The key: 7 hex digits of the type name's MurmurHash3 (what Blender looks up).
        key = f"cryptomatte/{mmh3.hash(type_name, 0, signed=False):08x}"[:19]
        assert spec.getattribute(f"{key}/name") == type_name
        assert spec.getattribute(f"{key}/hash") == "MurmurHash3_32"
        assert spec.getattribute(f"{key}/conversion") == "uint32_to_float32"
        manifest = json.loads(spec.getattribute(f"{key}/manifest"))
        assert set(manifest) == names, type_name
        for name, hex_id in manifest.items():
            assert hex_id == id_hex(name), name


def test_a_pixel_names_what_covers_it(rendered):
    _, _, _, pick, png, outside = rendered
    wheel = pick["wheel"]
    assert wheel["samples"] == SPP
    assert [(m["name"], m["coverage"]) for m in wheel["objects"]] == [("wheel", 1.0)]
    assert wheel["materials"][0]["name"] == "rubber" and wheel["assets"][0]["name"] == "car"
    assert wheel["objects"][0]["id"] == id_hex("wheel")
    assert [m["name"] for m in pick["lamp"]["assets"]] == ["lamp"]
    assert pick["nothing"]["objects"] == [] and pick["nothing"]["samples"] == SPP
    assert outside.status == 400 and outside.field == "x"
    assert png.startswith(b"\x89PNG")


def test_blenders_cryptomatte_node_extracts_the_same_mattes(rendered):
    _, exr, out, _, _, _ = rendered
    wanted = ["CryptoObject=wheel", "CryptoObject=body", "CryptoAsset=car",
              "CryptoMaterial=paint"]  # fmt: skip
    args = [str(out / "car.exr"), str(W), str(H), str(out), *wanted]
    written = run_blender_script(SCRIPT, args, out)
    exact = exact_coverage()
    expected = {
        "CryptoObject=wheel": exact["wheel"],
        "CryptoObject=body": exact["body"],
        "CryptoAsset=car": exact["body"] + exact["wheel"],
        "CryptoMaterial=paint": exact["body"] + exact["lamp"],
    }
    for key, path in written.items():
        blender = read_exr(path)["R"].astype(np.float64)
        type_name, name = key.split("=")
        # Blender's decoding of the farm's EXR gives the farm's coverage ...
        np.testing.assert_allclose(blender, matte(exr, type_name, name), atol=1e-6, err_msg=key)
        # ... which is the shape's area in each pixel, within the samples' noise.
        within_noise(blender, expected[key], key)
