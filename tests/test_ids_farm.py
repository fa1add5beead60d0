"""The `ids` outputs on a real farm (#40): instance and material labels of a scene whose answer is
known by construction. A camera at the origin looking down -Z sees, on the plane z = -3, three
quads filling three quadrants of the image, each exactly on pixel boundaries (the image's centre
lines), and nothing in the fourth:

- top right: node 3, a mesh used once (the renderer merges it into its world mesh) placed under
  an empty parent (node 1), with no material (glTF's default: label 0), behind node 2's quad,
  whose MASK material is transparent everywhere (the ray goes through it);
- bottom left and bottom right: nodes 4 and 5, two nodes of one shared mesh (instances), whose
  primitive has material 1, or material 3 under the variant "red" (KHR_materials_variants).

The expected labels are the glTF indices plus one, read off the scene's own JSON."""

from __future__ import annotations

import base64
import json
import math

import numpy as np
import pytest

from renderfarm.client import Client
from renderfarm.infra.images import read_exr

from .waiting import wait_until

W, H = 32, 24
YFOV = 0.8
Z = 3.0  # the quads' distance
HALF_Y = Z * math.tan(YFOV / 2)  # half the image's height on the plane
HALF_X = HALF_Y * W / H
SETTINGS = {"width": W, "height": H, "tile_size": 16, "max_spp": 2, "noise_threshold": 0,
            "aovs": ["ids", "depth"]}  # fmt: skip
DATA_URI = "data:application/octet-stream;base64,"


def node(name: str, mesh: int | None = None, at=(0.0, 0.0, 0.0), size=(1.0, 1.0), **more):
    """A node placing the unit quad [0, 1]^2 (z = 0) of `mesh` at `at`, scaled to `size`."""
    out = {"name": name, "translation": list(at), "scale": [size[0], size[1], 1.0], **more}
    if mesh is not None:
        out["mesh"] = mesh
    return out


def scene() -> dict:
    quad = np.array([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)], np.float32)
    indices = np.array([0, 1, 2, 0, 2, 3], np.uint16)
    blob = quad.tobytes() + indices.tobytes()
    primitive = {"attributes": {"POSITION": 0}, "indices": 1}
    big = (HALF_X + 1, HALF_Y + 1)  # a quadrant and more (past the image's edges)
    return {
        "asset": {"version": "2.0"},
        "extensionsUsed": ["KHR_materials_variants"],
        "extensions": {"KHR_materials_variants": {"variants": [{"name": "red"}]}},
        "scene": 0,
        "scenes": [{"nodes": [0, 1, 2, 4, 5]}],
        "nodes": [
            {"name": "camera", "camera": 0},
            # An empty parent: node 3 is at (0, 0, -1) + (0, 0, -2) = z -3.
            {"name": "group", "translation": [0, 0, -1], "children": [3]},
            node("glass", 2, (0, 0, -2), big),
            node("single", 0, (0, 0, -2), big),
            node("shared a", 1, (-big[0], -big[1], -Z), big),
            node("shared b", 1, (0, -big[1], -Z), big),
        ],
        "cameras": [{"type": "perspective",
                     "perspective": {"yfov": YFOV, "aspectRatio": W / H, "znear": 0.05}}],
        "meshes": [
            {"name": "no material", "primitives": [primitive]},
            {"name": "shared", "primitives": [{
                **primitive, "material": 1,
                "extensions": {"KHR_materials_variants": {
                    "mappings": [{"material": 3, "variants": [0]}]}},
            }]},
            {"name": "mask", "primitives": [{**primitive, "material": 2}]},
        ],
        "materials": [
            {"name": "unused"},
            {"name": "grey", "emissiveFactor": [0.5, 0.5, 0.5], "doubleSided": True},
            {"name": "holes", "alphaMode": "MASK", "doubleSided": True,
             "pbrMetallicRoughness": {"baseColorFactor": [1, 1, 1, 0]}},
            {"name": "red", "emissiveFactor": [1, 0, 0], "doubleSided": True},
        ],
        "buffers": [{"byteLength": len(blob), "uri": DATA_URI + base64.b64encode(blob).decode()}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 48},
                        {"buffer": 0, "byteOffset": 48, "byteLength": 12}],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3",
             "min": [0, 0, 0], "max": [1, 1, 0]},
            {"bufferView": 1, "componentType": 5123, "count": 6, "type": "SCALAR"},
        ],
    }  # fmt: skip


def expected(doc: dict, variant: bool) -> tuple[np.ndarray, np.ndarray]:
    """(instance, material) labels per pixel from the scene's JSON: each quadrant's node and
    its primitive's material (the variant's mapping applied), plus one; 0 for none."""
    names = [n["name"] for n in doc["nodes"]]
    shared = doc["meshes"][1]["primitives"][0]
    material = shared["extensions"]["KHR_materials_variants"]["mappings"][0]["material"]
    shared_material = (material if variant else shared["material"]) + 1
    instance = np.zeros((H, W), np.uint32)
    labels = np.zeros((H, W), np.uint32)
    instance[: H // 2, W // 2 :] = names.index("single") + 1  # no material: 0
    instance[H // 2 :, : W // 2] = names.index("shared a") + 1
    instance[H // 2 :, W // 2 :] = names.index("shared b") + 1
    labels[H // 2 :, :] = shared_material
    return instance, labels


def near_centre_lines() -> np.ndarray:
    """Pixels next to the image's centre lines, where the quads meet: a sample exactly on an
    edge may hit either side (in float32), so those pixels may hold a neighbour's label."""
    mask = np.zeros((H, W), bool)
    mask[H // 2 - 1 : H // 2 + 1, :] = True
    mask[:, W // 2 - 1 : W // 2 + 1] = True
    return mask


@pytest.fixture(scope="module")
def labels(farm, tmp_path_factory):
    out = tmp_path_factory.mktemp("ids")
    path = out / "quads.gltf"
    doc = scene()
    path.write_text(json.dumps(doc))
    with Client(farm.url, timeout=120) as client:
        wait_until(lambda: len(client.workers()) >= 1, 30, "a worker connected")
        jobs = {
            "default": client.submit(str(path), settings=SETTINGS, name="ids"),
            "red": client.submit(str(path), settings={**SETTINGS, "variant": "red"}, name="red"),
        }
        exrs, pngs = {}, {}
        for key, job in jobs.items():
            done = client.wait(job["id"], poll_s=0.2, timeout_s=600)
            assert done["state"] == "completed", done
            client.save_image(job["id"], out / f"{key}.exr", "exr")
            exrs[key] = read_exr(str(out / f"{key}.exr"))
        for layer in ("instance", "material"):
            pngs[layer] = client.image(jobs["default"]["id"], "png", layer=layer)
    return doc, exrs, pngs


def _check(got: np.ndarray, want: np.ndarray, what: str) -> None:
    inner = ~near_centre_lines()
    assert got.dtype == np.float32 and got.shape == (H, W)
    assert np.array_equal(got, np.round(got)), f"{what}: not integers"
    np.testing.assert_array_equal(got[inner], want[inner], err_msg=what)
    # Next to the centre lines: the label of one of the pixel's neighbours on the other side.
    for j, i in zip(*np.nonzero(~inner), strict=True):
        around = want[max(0, j - 1) : j + 2, max(0, i - 1) : i + 2]
        assert got[j, i] in around, (what, i, j)


def test_instance_and_material_are_the_first_hits_gltf_indices_plus_one(labels):
    doc, exrs, _ = labels
    instance, material = expected(doc, variant=False)
    # Not vacuous: the three nodes and the background, two materials and none.
    assert set(np.unique(instance)) == {0, 4, 5, 6} and set(np.unique(material)) == {0, 2}
    _check(exrs["default"]["instance.id"], instance, "instance")
    _check(exrs["default"]["material.id"], material, "material")
    # The MASK quad in front of node 3 was gone through: its depth is node 3's plane.
    depth = exrs["default"]["depth.Z"]
    np.testing.assert_allclose(depth[: H // 2 - 1, W // 2 + 1 :], Z, rtol=1e-5)
    assert (depth[: H // 2 - 1, : W // 2 - 1] == 1e10).all()


def test_a_variant_relabels_the_materials_not_the_instances(labels):
    doc, exrs, _ = labels
    instance, material = expected(doc, variant=True)
    assert set(np.unique(material)) == {0, 4}
    _check(exrs["red"]["instance.id"], instance, "instance")
    _check(exrs["red"]["material.id"], material, "material")


def test_label_pngs_colour_each_label_and_leave_the_background_black(labels, tmp_path):
    import OpenImageIO as oiio

    doc, _, pngs = labels
    instance, _ = expected(doc, variant=False)
    path = tmp_path / "instance.png"
    path.write_bytes(pngs["instance"])
    pixels = oiio.ImageBuf(str(path)).get_pixels(oiio.UINT8)
    assert pixels.shape == (H, W, 3)
    inner = ~near_centre_lines()
    colours = {}
    for label in (0, 4, 5, 6):
        seen = {tuple(p) for p in pixels[inner & (instance == label)]}
        assert len(seen) == 1, (label, seen)  # one colour per label
        colours[label] = seen.pop()
    assert colours[0] == (0, 0, 0)
    assert len(set(colours.values())) == 4  # each label its own colour
    assert pngs["material"].startswith(b"\x89PNG")
