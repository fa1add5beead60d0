"""The camera of a job's image, as the renderer used it (docs/usage.md, "Camera data"): what
synthetic-data pipelines need to go from pixels to rays and back.

The worker says where its camera is (`renderfarm-worker camera`: position, the unit axes
right, up and forward, yfov or xmag/ymag, znear, zfar; infra/scene_check.py runs it). This
module turns that into intrinsics for the job's image size and the matrices between world and
camera space, and into the EXR header's standard attributes. Pure arithmetic, no I/O.

How the renderer makes a camera ray (worker/src/scene/scene.cpp, Camera::raster): image
position (px, py), continuous, x right and y down, pixel (i, j) covering [i, i+1) x [j, j+1),
maps onto the image plane as

    perspective:  direction = forward + right * sx + up * sy
    orthographic: origin    = position + right * sx + up * sy, direction = forward
    sx = (2 px / W - 1) hw,   sy = (1 - 2 py / H) hh

with hh = tan(yfov / 2) and hw = hh W / H (glTF's aspectRatio is not used: pixels are
square), or hw = xmag and hh = ymag. Solved for (px, py) with camera-space coordinates
(x, y, z) (glTF's: looking down -Z, +Y up) that is the pinhole

    u = cx + fx x / (-z),   v = cy - fy y / (-z)      (orthographic: u = cx + fx x, v = cy - fy y)

with fy = (H / 2) / tan(yfov / 2) = fx, or fx = W / (2 xmag), fy = H / (2 ymag) in pixels per
unit of length, and (cx, cy) = (W / 2, H / 2): the centre of pixel (i, j) is (i + 0.5, j + 0.5).
"""

from __future__ import annotations

import math
from typing import Any

CONVENTION = (
    "glTF camera space: right-handed, the camera at the origin looking down -Z, +X right and "
    "+Y up in the image; u = cx + fx * x / -z, v = cy - fy * y / -z (orthographic: "
    "u = cx + fx * x, v = cy - fy * y), in pixels from the image's top-left corner, +v down "
    "the rows, the centre of pixel (i, j) at (i + 0.5, j + 0.5)"
)

Matrix = list[list[float]]


def _dot(a: list[float], b: list[float]) -> float:
    return sum(x * y for x, y in zip(a, b, strict=True))


def _cross(a: list[float], b: list[float]) -> list[float]:
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def _unit(a: list[float]) -> list[float]:
    norm = math.sqrt(_dot(a, a))
    return [v / norm + 0.0 for v in a]


def _transpose(m: Matrix) -> Matrix:
    return [list(row) for row in zip(*m, strict=True)]


def _product(a: Matrix, b: Matrix) -> Matrix:
    return [[_dot(row, col) for col in _transpose(b)] for row in a]


def frame_camera(
    pose: dict[str, Any],
    width: int,
    height: int,
    frame: int,
    time_s: float | None,
    shutter_s: tuple[float, float] | None = None,
) -> dict[str, Any]:
    """camera.json of one image: `pose` is one camera of the worker's `camera` command, the
    image width x height pixels, `frame` its number (0 for a still, the index of a variant),
    `time_s` the glTF time it is posed at (None: a still, the scene as stored), `shutter_s`
    the glTF times a motion-blurred frame's shutter opens and closes (the camera data is the
    frame's time's, wherever the shutter is)."""
    # The loader's axes are orthonormal to float precision (2^-24): made so again in double,
    # as the loader does (right = forward x up, up = right x forward), so that the matrices
    # below are each other's inverse to double precision. (+ 0.0 makes a -0.0 a 0.0.)
    position = [float(v) + 0.0 for v in pose["position"]]
    forward = _unit([float(v) for v in pose["forward"]])
    right = _unit(_cross(forward, [float(v) for v in pose["up"]]))
    up = [v + 0.0 for v in _cross(right, forward)]
    back = [0.0 - v for v in forward]  # camera +Z
    # Columns: the camera's axes and position in world space.
    camera_to_world = [
        [right[0], up[0], back[0], position[0]],
        [right[1], up[1], back[1], position[1]],
        [right[2], up[2], back[2], position[2]],
        [0.0, 0.0, 0.0, 1.0],
    ]
    world_to_camera = [
        [*right, 0.0 - _dot(right, position)],
        [*up, 0.0 - _dot(up, position)],
        [*back, 0.0 - _dot(back, position)],
        [0.0, 0.0, 0.0, 1.0],
    ]
    if pose["projection"] == "orthographic":
        xmag, ymag = float(pose["xmag"]), float(pose["ymag"])
        fx, fy, yfov = width / (2 * xmag), height / (2 * ymag), None
    else:
        xmag = ymag = None
        yfov = float(pose["yfov"])
        fx = fy = (height / 2) / math.tan(yfov / 2)
    return {
        "frame": frame,
        "time_s": time_s,
        "shutter_s": list(shutter_s) if shutter_s else None,
        "projection": pose["projection"],
        "width": width,
        "height": height,
        "fx": fx,
        "fy": fy,
        "cx": width / 2,
        "cy": height / 2,
        "yfov": yfov,
        "xmag": xmag,
        "ymag": ymag,
        "world_to_camera": world_to_camera,
        "camera_to_world": camera_to_world,
        "convention": CONVENTION,
        "near": float(pose["znear"]),
        "far": None if pose.get("zfar") is None else float(pose["zfar"]),
        "node": pose.get("node"),
    }


def exr_matrices(camera: dict[str, Any]) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """OpenEXR's standard attributes worldToCamera and worldToNDC (Imath M44f) of a camera of
    frame_camera, as 16 floats in Imath's order (m[0][0], m[0][1], ...): Imath multiplies row
    vectors, p' = p M, so each is the transpose of the column-vector matrix.

    worldToCamera: OpenEXR's camera space is left-handed, +Z the viewing direction, +X right
    and +Y up: glTF's camera space with z negated. worldToNDC: NDC (0, 0) is the top-left
    corner of the image and (1, 1) its bottom-right, x right and y down: (u / W, v / H) after
    the homogeneous divide; z / w is 1 / depth (perspective) or the depth (orthographic)."""
    flip = [[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, -1.0, 0], [0, 0, 0, 1.0]]
    to_camera = _product(flip, camera["world_to_camera"])  # OpenEXR's camera space
    w, h = camera["width"], camera["height"]
    fx, fy, cx, cy = camera["fx"], camera["fy"], camera["cx"], camera["cy"]
    if camera["projection"] == "orthographic":
        ndc = [[fx / w, 0, 0, cx / w], [0, -fy / h, 0, cy / h], [0, 0, 1, 0], [0, 0, 0, 1]]
    else:  # (x, y, d) -> (fx x / W + cx d / W, -fy y / H + cy d / H, 1, d)
        ndc = [[fx / w, 0, cx / w, 0], [0, -fy / h, cy / h, 0], [0, 0, 0, 1], [0, 0, 1, 0]]
    to_ndc = _product(ndc, to_camera)

    def imath(m: Matrix) -> tuple[float, ...]:
        return tuple(float(v) for row in _transpose(m) for v in row)

    return imath(to_camera), imath(to_ndc)
