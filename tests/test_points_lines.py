"""Points and lines (glTF primitive modes 0-3) against the glTF 2.0 specification's "Point and
Line Materials" conventions, which the farm follows:

- "Points and Lines SHOULD have widths of 1px in viewport space": each point covers one pixel
  of area and each line one pixel of area per pixel of its length, so the image's pixel values
  summed over a line's columns (or over a point's neighbourhood) are its radiance times one.
- "Points or Lines with no NORMAL attribute SHOULD be rendered without lighting and instead use
  the sum of the base color value (as defined above, multiplied by COLOR_0 when present) and the
  emissive value."
- "Points or Lines with NORMAL but without TANGENT attributes SHOULD be rendered with standard
  lighting but ignoring any normal textures": under one directional light and an orthographic
  camera, a lit line's radiance is Appendix B's BRDF with the line's NORMAL, which
  tests/test_brdf_spec.py's spec_brdf evaluates in numpy.

The expected values come from those sentences and that closed form, not from the renderer.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest

from renderfarm.domain.scenes.glb import build_glb
from renderfarm.infra.images import read_exr

from .test_brdf_spec import direction, frame_matrix, spec_brdf

WIDTH, HEIGHT = 96, 48
YMAG = 1.5  # orthographic: a pixel is 2 YMAG / HEIGHT world units
PIXEL = 2 * YMAG / HEIGHT
BASE = (0.2, 0.4, 0.6)
EMISSIVE = (0.1, 0.05, 0.0)
INTENSITY = 2.0
MODES = {"POINTS": 0, "LINES": 1, "LINE_LOOP": 2, "LINE_STRIP": 3}


def thin_scene(
    path: Path,
    points: np.ndarray,
    mode: int,
    *,
    normals: np.ndarray | None = None,
    colours: np.ndarray | None = None,
    camera: dict | None = None,
    view: np.ndarray | None = None,
    light: np.ndarray | None = None,
    roughness: float = 0.5,
    animation: tuple[list[float], list[list[float]]] | None = None,
) -> None:
    """One primitive of `mode` over `points` (world space, camera looking along -view from 30
    units out; image right is world +Z, up the rest), a directional light shining along
    -light, a black world. animation: (times, translations) of the primitive's node."""
    view = np.array([1.0, 0.0, 0.0]) if view is None else view
    light = direction(45.0, 20.0) if light is None else light
    pos = np.asarray(points, np.float32)
    n = len(pos)
    blob = pos.tobytes()
    views = [{"buffer": 0, "byteOffset": 0, "byteLength": 12 * n}]
    accessors = [{"bufferView": 0, "componentType": 5126, "count": n, "type": "VEC3",
                  "min": pos.min(0).tolist(), "max": pos.max(0).tolist()}]  # fmt: skip
    attributes = {"POSITION": 0}
    for name, data in (("NORMAL", normals), ("COLOR_0", colours)):
        if data is None:
            continue
        arr = np.asarray(data, np.float32)
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": arr.nbytes})
        accessors.append({"bufferView": len(views) - 1, "componentType": 5126, "count": n,
                          "type": "VEC3"})  # fmt: skip
        attributes[name] = len(accessors) - 1
        blob += arr.tobytes()
    node = {"mesh": 0}
    gltf = {
        "asset": {"version": "2.0"},
        "extensionsUsed": ["KHR_lights_punctual"],
        "extensions": {"KHR_lights_punctual": {"lights": [
            {"type": "directional", "color": [1, 1, 1], "intensity": INTENSITY}]}},
        "scene": 0,
        "scenes": [{"nodes": [0, 1, 2]}],
        "nodes": [
            node,
            {"camera": 0, "matrix": frame_matrix(view, np.array([0.0, 0.0, 1.0]), 30.0 * view)},
            {"matrix": frame_matrix(light, np.array([0.3, 0.1, 0.9]), 10.0 * light),
             "extensions": {"KHR_lights_punctual": {"light": 0}}},
        ],
        "cameras": [camera or {"type": "orthographic", "orthographic": {
            "xmag": YMAG * WIDTH / HEIGHT, "ymag": YMAG, "znear": 0.1, "zfar": 100.0}}],
        "meshes": [{"primitives": [{"attributes": attributes, "mode": mode, "material": 0}]}],
        "materials": [{"pbrMetallicRoughness": {"baseColorFactor": [*BASE, 1.0],
                                                "metallicFactor": 0.0,
                                                "roughnessFactor": roughness},
                       "emissiveFactor": list(EMISSIVE)}],
        "accessors": accessors,
        "bufferViews": views,
    }  # fmt: skip
    if animation:
        times, translations = animation
        t = np.asarray(times, np.float32)
        v = np.asarray(translations, np.float32)
        for arr, kind in ((t, "SCALAR"), (v, "VEC3")):
            views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": arr.nbytes})
            accessor = {"bufferView": len(views) - 1, "componentType": 5126,
                        "count": len(arr), "type": kind}  # fmt: skip
            if kind == "SCALAR":
                accessor |= {"min": [float(t.min())], "max": [float(t.max())]}
            accessors.append(accessor)
            blob += arr.tobytes()
        gltf["animations"] = [{
            "samplers": [{"input": len(accessors) - 2, "output": len(accessors) - 1}],
            "channels": [{"sampler": 0,
                          "target": {"node": 0, "path": "translation"}}]}]  # fmt: skip
    gltf["buffers"] = [{"byteLength": len(blob)}]
    path.write_bytes(build_glb(gltf, blob))


def render(worker: str, scene: Path, *extra: str, spp: int = 64) -> tuple[np.ndarray, str]:
    out = scene.with_suffix(".exr")
    proc = subprocess.run([worker, "render", str(scene), "-o", str(out), "--spp", str(spp),
                           "--width", str(WIDTH), "--height", str(HEIGHT), "--threads", "1",
                           "--max-depth", "2", *extra],
                          check=True, capture_output=True, text=True, timeout=120)  # fmt: skip
    channels = read_exr(str(out))
    image = np.stack([channels["R"], channels["G"], channels["B"]], -1).astype(np.float64)
    return image, proc.stderr


def line_across(y: float, z0: float = -40.0, z1: float = 40.0) -> np.ndarray:
    """A segment along world +Z (image right) at height y, past both image edges."""
    return np.array([[0.0, y, z0], [0.0, y, z1]])


UNLIT = np.asarray(BASE) + np.asarray(EMISSIVE)


@pytest.mark.parametrize("y", [0.0, 0.37 * PIXEL, 5.5 * PIXEL])
def test_an_unlit_line_is_one_pixel_of_base_colour_plus_emission_per_column(
    tmp_path: Path, worker_binary: str, y: float
) -> None:
    scene = tmp_path / "line.glb"
    thin_scene(scene, line_across(y), MODES["LINES"])
    image, stderr = render(worker_binary, scene)
    assert "points or lines" not in stderr, stderr
    columns = image.sum(axis=0)  # per column: the line's radiance x its width in pixels
    np.testing.assert_allclose(columns.mean(0), UNLIT, rtol=0.01)
    np.testing.assert_allclose(columns, np.broadcast_to(UNLIT, columns.shape), rtol=0.08)
    # The line is where it is: its row, from the camera's projection (image down is world +Y
    # for this camera: its up is cross(view, right) = cross(+X, +Z) = -Y).
    row = HEIGHT / 2 + y / PIXEL
    weights = image[..., 2].sum(axis=1)
    centre = float((weights * (np.arange(HEIGHT) + 0.5)).sum() / weights.sum())
    assert abs(centre - row) < 0.05, (centre, row)


def test_vertex_colours_multiply_the_base_colour_of_unlit_lines(
    tmp_path: Path, worker_binary: str
) -> None:
    scene = tmp_path / "coloured.glb"
    colour = np.array([0.5, 1.0, 0.25])
    thin_scene(scene, line_across(0.1), MODES["LINES"], colours=np.array([colour, colour]))
    image, _ = render(worker_binary, scene)
    want = np.asarray(BASE) * colour + np.asarray(EMISSIVE)
    np.testing.assert_allclose(image.sum(axis=0).mean(0), want, rtol=0.01)


def test_a_perspective_line_is_one_pixel_wide_at_its_depth(
    tmp_path: Path, worker_binary: str
) -> None:
    # A pinhole 30 units out: a line across the view at depth 30 (x = 0) and one at depth 12
    # (x = 18) are each one pixel wide where they are.
    camera = {"type": "perspective", "perspective": {"yfov": 0.5, "aspectRatio": 2.0,
                                                      "znear": 0.1}}  # fmt: skip
    for depth in (30.0, 12.0):
        scene = tmp_path / f"perspective-{depth:g}.glb"
        points = line_across(0.05) + np.array([30.0 - depth, 0.0, 0.0])
        thin_scene(scene, points, MODES["LINES"], camera=camera)
        image, _ = render(worker_binary, scene)
        np.testing.assert_allclose(image.sum(axis=0).mean(0), UNLIT, rtol=0.01, err_msg=depth)


def test_points_are_one_pixel_each(tmp_path: Path, worker_binary: str) -> None:
    grid = [
        [0.0, (j - 1) * 9.3 * PIXEL, (i - 2) * 11.7 * PIXEL] for i in range(5) for j in range(3)
    ]
    scene = tmp_path / "points.glb"
    thin_scene(scene, np.array(grid), MODES["POINTS"])
    image, _ = render(worker_binary, scene)
    np.testing.assert_allclose(image.sum(axis=(0, 1)), len(grid) * UNLIT, rtol=0.01)


@pytest.mark.parametrize("mode", ["LINE_LOOP", "LINE_STRIP"])
def test_strips_and_loops_draw_every_segment(tmp_path: Path, worker_binary: str, mode: str) -> None:
    # A square of side 20 pixels: a loop closes it (four sides, four corners), a strip leaves
    # the last one out (three sides, two corners). Each segment is one pixel wide and ends
    # square at its vertices, so at a right-angled corner two of them overlap on a half-pixel
    # square: the ink is the length in pixels less a quarter of a pixel per corner.
    s = 10 * PIXEL
    square = np.array([[0.0, -s, -s], [0.0, -s, s], [0.0, s, s], [0.0, s, -s]])
    scene = tmp_path / f"{mode}.glb"
    thin_scene(scene, square, MODES[mode])
    image, _ = render(worker_binary, scene)
    sides, corners = (4, 4) if mode == "LINE_LOOP" else (3, 2)
    area = sides * 20 - corners * 0.25
    np.testing.assert_allclose(image.sum(axis=(0, 1)), area * UNLIT, rtol=0.002)


@pytest.mark.parametrize("light_deg", [(30.0, 10.0), (70.0, 60.0)])
def test_a_line_with_normals_is_lit_as_the_spec_brdf_says(
    tmp_path: Path, worker_binary: str, light_deg: tuple[float, float]
) -> None:
    # NORMAL +Y along the line, the camera 35 degrees above the horizon: the line's radiance is
    # I f(V, L) N.L with N its NORMAL, not the ribbon's own facing.
    view, light = direction(35.0, 0.0), direction(*light_deg)
    scene = tmp_path / "lit.glb"
    normals = np.array([[0.0, 1.0, 0.0]] * 2)
    thin_scene(scene, line_across(0.0), MODES["LINES"], normals=normals, view=view, light=light)
    image, _ = render(worker_binary, scene)
    want = INTENSITY * spec_brdf(BASE, 0.5, 1.5, 1.0, (1.0, 1.0, 1.0), v=view, light=light)
    want = want * light[1] + np.asarray(EMISSIVE)
    np.testing.assert_allclose(image.sum(axis=0).mean(0), want, rtol=0.01)


def test_an_animated_line_moves_with_its_node(tmp_path: Path, worker_binary: str) -> None:
    # The node moves 8 pixels along +Y (image down) from time 0 to 1: at time 0.5 the line is
    # 4 pixels below the centre, still one pixel wide (the pose's own triangles).
    scene = tmp_path / "moving.glb"
    thin_scene(scene, line_across(0.0), MODES["LINES"],
               animation=([0.0, 1.0], [[0.0, 0.0, 0.0], [0.0, 8 * PIXEL, 0.0]]))  # fmt: skip
    image, _ = render(worker_binary, scene, "--time", "0.5")
    np.testing.assert_allclose(image.sum(axis=0).mean(0), UNLIT, rtol=0.01)
    weights = image[..., 2].sum(axis=1)
    centre = float((weights * (np.arange(HEIGHT) + 0.5)).sum() / weights.sum())
    assert abs(centre - (HEIGHT / 2 + 4)) < 0.05, centre


def test_a_mode_that_is_not_a_primitive_mode_is_refused_by_its_path(
    tmp_path: Path, worker_binary: str
) -> None:
    scene = tmp_path / "mode7.glb"
    thin_scene(scene, line_across(0.0), 7)
    proc = subprocess.run([worker_binary, "render", str(scene), "-o", str(tmp_path / "x.exr"),
                           "--spp", "1", "--width", "8", "--height", "8"],
                          capture_output=True, text=True, timeout=60)  # fmt: skip
    assert proc.returncode != 0
    assert "meshes[0].primitives[0].mode: 7 is not a glTF primitive mode" in proc.stderr
