"""The light_groups output on a real farm (#40): a Lambert wall lit by three point lights, two
of them grouped by extras.light_group, under a uniform environment, with an emissive panel on
it, seen by a pinhole camera with max_depth 1 (direct light only). The answers need no
renderer:

- each group's light on the wall is I cos(theta) / d^2 of its lights times one factor (the
  wall's albedo / pi and the renderer's unit of intensity), so the groups' images over the wall
  are in the ratio of those sums;
- the environment lights the wall with albedo x E and is E where the camera sees the sky;
- the panel shows its emission, in its own group, and lights nothing the camera sees;
- on every pixel the groups sum to the image."""

from __future__ import annotations

import base64
import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest

from renderfarm.client import ApiError, Client
from renderfarm.infra.images import read_exr

from .test_lobes_farm import uniform_hdr
from .waiting import wait_until

W, H = 48, 32
YFOV = 0.7
WALL_Z = -4.0
E = 0.25  # the environment's radiance
ALBEDO = 0.8
PANEL = (0.9, 0.6, 1.6, 1.2)  # x0, y0, x1, y1 on the wall
GLOW = (3.0, 2.0, 1.0)
# name, position, intensity, extras.light_group
LIGHTS = [
    ("key", (-1.5, 1.0, -2.0), 8.0, None),
    ("fill_a", (1.5, 0.5, -3.0), 2.0, "fill"),
    ("fill_b", (0.5, -0.5, -3.5), 1.0, "fill"),
]
SETTINGS = {"width": W, "height": H, "tile_size": 16, "max_spp": 64, "noise_threshold": 0,
            "max_depth": 1, "aovs": ["light_groups"]}  # fmt: skip
DATA_URI = "data:application/octet-stream;base64,"
HALF_H = -WALL_Z * math.tan(YFOV / 2)
SKY_Y = -1.0  # the wall's bottom edge: below it the camera sees the environment


def scene() -> dict:
    wall = np.array([(-6, SKY_Y, 0), (6, SKY_Y, 0), (6, 6, 0), (-6, 6, 0)], np.float32)
    x0, y0, x1, y1 = PANEL
    panel = np.array([(x0, y0, 0), (x1, y0, 0), (x1, y1, 0), (x0, y1, 0)], np.float32)
    indices = np.array([0, 1, 2, 0, 2, 3], np.uint16)
    blob, views = b"", []
    for part in (wall, panel, indices):
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": part.nbytes})
        blob += part.tobytes() + b"\0" * (-part.nbytes % 4)
    nodes = [
        {"name": "wall", "mesh": 0, "translation": [0, 0, WALL_Z]},
        {"name": "panel", "mesh": 1, "translation": [0, 0, WALL_Z + 1e-3]},
        {"name": "camera", "camera": 0},
    ]
    for name, position, _, group in LIGHTS:
        node = {"name": name, "translation": list(position),
                "extensions": {"KHR_lights_punctual": {"light": len(nodes) - 3}}}  # fmt: skip
        if group:
            node["extras"] = {"light_group": group}
        nodes.append(node)
    return {
        "asset": {"version": "2.0"},
        "extensionsUsed": ["KHR_lights_punctual", "KHR_materials_specular"],
        "extensions": {"KHR_lights_punctual": {"lights": [
            {"type": "point", "intensity": intensity, "color": [1, 1, 1]}
            for _, _, intensity, _ in LIGHTS]}},
        "scene": 0,
        "scenes": [{"nodes": list(range(len(nodes)))}],
        "nodes": nodes,
        "cameras": [{"type": "perspective",
                     "perspective": {"yfov": YFOV, "aspectRatio": W / H, "znear": 0.05}}],
        "meshes": [
            {"primitives": [{"attributes": {"POSITION": 0}, "indices": 2, "material": 0}]},
            {"primitives": [{"attributes": {"POSITION": 1}, "indices": 2, "material": 1}]},
        ],
        "materials": [
            {"name": "wall", "pbrMetallicRoughness": {
                "baseColorFactor": [ALBEDO, ALBEDO, ALBEDO, 1], "metallicFactor": 0},
             "extensions": {"KHR_materials_specular": {"specularFactor": 0}}},
            {"name": "glow", "emissiveFactor": list(GLOW), "pbrMetallicRoughness": {
                "baseColorFactor": [0, 0, 0, 1], "metallicFactor": 0},
             "extensions": {"KHR_materials_specular": {"specularFactor": 0}}},
        ],
        "buffers": [{"byteLength": len(blob), "uri": DATA_URI + base64.b64encode(blob).decode()}],
        "bufferViews": views,
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3",
             "min": [-6, SKY_Y, 0], "max": [6, 6, 0]},
            {"bufferView": 1, "componentType": 5126, "count": 4, "type": "VEC3",
             "min": [x0, y0, 0], "max": [x1, y1, 0]},
            {"bufferView": 2, "componentType": 5123, "count": 6, "type": "SCALAR"},
        ],
    }  # fmt: skip


def pixel_grid() -> tuple[np.ndarray, np.ndarray]:
    """Where each pixel's centre ray meets the wall's plane (x, y)."""
    f = (H / 2) / HALF_H
    i, j = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    return (i - W / 2) / f, (H / 2 - j) / f


def irradiance(names: list[str]) -> np.ndarray:
    """Sum of I cos(theta) / d^2 of the named lights at each pixel's point of the wall."""
    x, y = pixel_grid()
    total = np.zeros((H, W))
    for name, (lx, ly, lz), intensity, _ in LIGHTS:
        if name in names:
            dz = lz - WALL_Z
            d2 = (lx - x) ** 2 + (ly - y) ** 2 + dz**2
            total += intensity * dz / d2**1.5
    return total


def regions() -> dict[str, np.ndarray]:
    x, y = pixel_grid()
    f = (H / 2) / HALF_H
    margin = 1.0 / f  # a pixel: away from the edges
    x0, y0, x1, y1 = PANEL
    panel = (x > x0 - margin) & (x < x1 + margin) & (y > y0 - margin) & (y < y1 + margin)
    inside = (x > x0 + margin) & (x < x1 - margin) & (y > y0 + margin) & (y < y1 - margin)
    return {
        "wall": (y > SKY_Y + margin) & ~panel,
        "panel": inside,
        "sky": y < SKY_Y - margin,
    }


@pytest.fixture(scope="module")
def grouped(farm, tmp_path_factory):
    out = tmp_path_factory.mktemp("light_groups")
    path = out / "lights.gltf"
    path.write_text(json.dumps(scene()))
    uniform_hdr(out / "sky.hdr", E)
    with Client(farm.url, timeout=120) as client:
        wait_until(lambda: len(client.workers()) >= 1, 30, "a worker connected")
        # A value given is replaced by the scene's groups.
        job = client.submit(
            str(path),
            name="light groups",
            settings={
                **SETTINGS,
                "environment": str(out / "sky.hdr"),
                "light_groups": {"bogus": [0]},
            },
        )
        done = client.wait(job["id"], poll_s=0.2, timeout_s=600)
        assert done["state"] == "completed", done
        client.save_image(job["id"], out / "groups.exr", "exr")
        png = client.image(job["id"], "png", layer="light_group", group="fill")
        with pytest.raises(ApiError) as refused:
            client.image(job["id"], "png", layer="light_group", group="nope")
        assert refused.value.status == 400 and "its groups: panel, key, fill" in str(refused.value)
    return done, read_exr(str(out / "groups.exr")), png


def group(exr: dict, name: str) -> np.ndarray:
    return np.stack([exr[f"light_group_{name}.{c}"] for c in "RGB"], -1).astype(np.float64)


def test_the_job_has_the_scenes_groups_in_node_order_and_the_environment_last(grouped):
    job, exr, png = grouped
    assert json.loads(job["settings"]["light_groups"]) == {
        "panel": [1],
        "key": [3],
        "fill": [4, 5],
        "environment": [],
    }
    # One RGB layer a group in the EXR (whose channels OpenEXR keeps sorted by name).
    groups = {c[len("light_group_") : -2] for c in exr if c.startswith("light_group_")}
    assert groups == {"panel", "key", "fill", "environment"}
    assert png.startswith(b"\x89PNG")


def test_the_groups_sum_to_the_image_on_every_pixel(grouped):
    _, exr, _ = grouped
    rgb = np.stack([exr[c] for c in "RGB"], -1).astype(np.float64)
    total = sum(group(exr, g) for g in ("panel", "key", "fill", "environment"))
    assert rgb.max() > 1.0  # the panel: not vacuous
    np.testing.assert_allclose(total, rgb, rtol=2e-5, atol=1e-6)


def test_each_groups_light_is_its_lights_and_nothing_else(grouped):
    _, exr, _ = grouped
    where = regions()
    for name, pixels in where.items():
        assert pixels.sum() >= 12, name
    key, fill = group(exr, "key")[..., 0], group(exr, "fill")[..., 0]
    wall = where["wall"]
    # The key and fill groups are in the ratio of their lights' I cos / d^2 over the wall
    # (light selection makes each pixel noisy; the sums over the wall are not).
    want = irradiance(["key"])[wall].sum() / irradiance(["fill_a", "fill_b"])[wall].sum()
    assert key[wall].sum() / fill[wall].sum() == pytest.approx(want, rel=0.03)
    # And each follows its own lights' shape: correlated with its irradiance, not the other's.
    assert np.corrcoef(key[wall], irradiance(["key"])[wall])[0, 1] > 0.9
    assert np.corrcoef(fill[wall], irradiance(["fill_a", "fill_b"])[wall])[0, 1] > 0.9
    # The environment lights the wall with albedo x E (a uniform hemisphere).
    environment = group(exr, "environment")
    env_wall = environment[wall]
    err = env_wall.std() / math.sqrt(env_wall.size)
    assert abs(env_wall.mean() - ALBEDO * E) < 4 * err + 1e-3
    # The sky: E, and nothing but the environment.
    np.testing.assert_allclose(environment[where["sky"]], E, rtol=1e-6)
    for g in ("panel", "key", "fill"):
        assert np.abs(group(exr, g)[where["sky"]]).max() == 0.0, g
    # The panel: its emission, and no other group's light (it reflects nothing).
    panel = group(exr, "panel")[where["panel"]]
    np.testing.assert_allclose(panel, np.broadcast_to(GLOW, panel.shape), rtol=1e-6)
    for g in ("key", "fill", "environment"):
        assert np.abs(group(exr, g)[where["panel"]]).max() == 0.0, g
    # It emits towards the camera, away from the wall: the wall gets none of its light.
    assert np.abs(group(exr, "panel")[wall]).max() == 0.0


def test_the_cli_gets_one_group_or_every_one(farm, grouped, tmp_path):
    job, exr, _ = grouped
    env = {**os.environ, "RENDERFARM_URL": farm.url}

    def cli(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "renderfarm", "get", job["id"], *args],
                              capture_output=True, text=True, timeout=300, env=env)  # fmt: skip

    done = cli("-o", str(tmp_path / "key.exr"), "--layer", "light_group", "--group", "key")
    assert done.returncode == 0, done.stderr
    key = read_exr(str(tmp_path / "key.exr"))
    assert sorted(key) == ["light_group_key.B", "light_group_key.G", "light_group_key.R"]
    assert key["light_group_key.G"].tobytes() == exr["light_group_key.G"].tobytes()
    done = cli("-o", str(tmp_path / "all.exr"), "--layer", "light_group")
    assert done.returncode == 0, done.stderr
    assert len(read_exr(str(tmp_path / "all.exr"))) == 4 * 3
    done = cli("-o", str(tmp_path / "fill.png"), "--layer", "light_group", "--group", "fill")
    assert done.returncode == 0 and (tmp_path / "fill.png").read_bytes()[:4] == b"\x89PNG"
    for args, code, words in [
        (("-o", str(tmp_path / "x.exr"), "--layer", "light_group", "--group", "nope"), 1,
         "no light group 'nope'; its groups: panel, key, fill, environment"),
        (("-o", str(tmp_path / "x.png"), "--layer", "rgb", "--group", "key"), 2,
         "--group picks a light group"),
    ]:  # fmt: skip
        done = cli(*args)
        assert done.returncode == code and words in done.stderr, done.stderr
