"""glTF animation, skins and morph targets as `renderfarm-worker pose` evaluates them, against
an independent numpy implementation of the glTF 2.0 specification written here: keyframe
sampling (3.11 and Appendix C: STEP, LINEAR with slerp on the shorter arc, CUBICSPLINE with
tangents scaled by the keyframe spacing), node transforms T R S composed down the hierarchy
(3.5.3), morph targets (3.7.2.2: base + sum of weighted displacements) and skins (3.7.3: the
vertex transformed by sum_i w_i globalJoint_i inverseBind_i over every JOINTS_n / WEIGHTS_n
set, the skinned node's own transform ignored). The scene is evaluated before its first key,
between keys, exactly on keys and after its last; then a frame is rendered at two times."""

from __future__ import annotations

import base64
import json
import subprocess
from pathlib import Path

import numpy as np
import pytest

from renderfarm.infra.images import read_exr

RTOL = 1e-5
ATOL = 1e-5

# ---- The scene: buffers built with numpy, embedded as a base64 data URI.


class GltfBuilder:
    def __init__(self) -> None:
        self.data = bytearray()
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def add(self, array, component_type: int, gltf_type: str, normalized: bool = False) -> int:
        dtype = {5121: np.uint8, 5123: np.uint16, 5126: np.float32}[component_type]
        arr = np.ascontiguousarray(np.asarray(array, dtype=dtype))
        while len(self.data) % 4:
            self.data.append(0)
        self.views.append({"buffer": 0, "byteOffset": len(self.data), "byteLength": arr.nbytes})
        self.data += arr.tobytes()
        width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4, "MAT4": 16}[gltf_type]
        flat = arr.reshape(-1, width)
        accessor = {
            "bufferView": len(self.views) - 1,
            "componentType": component_type,
            "count": flat.shape[0],
            "type": gltf_type,
        }
        if normalized:
            accessor["normalized"] = True
        if gltf_type in ("SCALAR", "VEC3") and component_type == 5126:
            accessor["min"] = flat.min(axis=0).astype(float).tolist()
            accessor["max"] = flat.max(axis=0).astype(float).tolist()
        self.accessors.append(accessor)
        return len(self.accessors) - 1

    def buffers(self) -> dict:
        uri = "data:application/octet-stream;base64," + base64.b64encode(self.data).decode()
        return {
            "bufferViews": self.views,
            "accessors": self.accessors,
            "buffers": [{"byteLength": len(self.data), "uri": uri}],
        }


def f32(a) -> np.ndarray:
    """The numbers as the file stores them (float32), back in float64."""
    return np.asarray(a, dtype=np.float32).astype(np.float64)


def quat_about(axis, angle: float) -> np.ndarray:
    axis = np.asarray(axis, float)
    axis = axis / np.linalg.norm(axis)
    return np.concatenate([axis * np.sin(angle / 2), [np.cos(angle / 2)]])


# Keyframes of the scene's samplers (times and outputs), shared by the file and the reference.
PARENT_ROT_TIMES = [0.5, 1.5, 2.5]
PARENT_ROT = [
    quat_about([0, 0, 1], 0.0),
    quat_about([0, 0, 1], np.pi / 2),
    # dot with the previous key < 0: the shorter arc is the negated quaternion's.
    quat_about([0.3, 0.2, 1.0], 300 * np.pi / 180),
]
CHILD_T_TIMES = [0.0, 1.0, 3.0]
# Per key: in-tangent, value, out-tangent.
CHILD_T = [
    [[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [1.0, 2.0, -1.0]],
    [[-0.5, 1.0, 0.25], [1.0, 1.0, 0.5], [0.75, -0.5, 0.0]],
    [[0.2, 0.2, 0.2], [2.0, -1.0, 1.0], [3.0, 3.0, 3.0]],
]
CHILD_S_TIMES = [0.5, 2.0]
CHILD_S = [[1.0, 1.0, 1.0], [2.0, 0.5, 1.5]]
WEIGHT_TIMES = [0.0, 1.0, 2.0]
WEIGHTS = [[0.0, 0.0], [1.0, 0.5], [0.25, 1.0]]
JOINT1_ROT_TIMES = [0.0, 2.0]
JOINT1_ROT = [quat_about([0, 0, 1], 0.0), quat_about([0, 1, 0.5], np.pi / 2)]
JOINT0_T_TIMES = [1.0]  # a single key: constant
JOINT0_T = [[0.0, 1.0, -2.0]]

NODE_TRS = {  # the nodes' own translation, rotation, scale
    0: dict(translation=[1.0, 2.0, 0.0]),
    1: dict(rotation=quat_about([1, 0, 0], np.pi / 6).tolist(), scale=[1.0, 1.0, 1.0]),
    2: dict(translation=[0.0, -3.0, 0.0]),
    3: dict(translation=[50.0, 0.0, 0.0]),  # skinned: ignored
    4: dict(translation=[0.0, 0.0, -2.0]),
    5: dict(translation=[1.0, 0.0, 0.0]),
    6: dict(translation=[1.0, 0.0, 0.0]),
    7: dict(translation=[0.0, 0.0, 5.0]),
}
PARENTS = {1: 0, 7: 0, 5: 4, 6: 5}
ANIMATIONS = [
    # (node, path, interpolation, times, outputs)
    [
        (0, "rotation", "LINEAR", PARENT_ROT_TIMES, PARENT_ROT),
        (1, "translation", "CUBICSPLINE", CHILD_T_TIMES, CHILD_T),
        (1, "scale", "STEP", CHILD_S_TIMES, CHILD_S),
        (2, "weights", "LINEAR", WEIGHT_TIMES, WEIGHTS),
    ],
    [
        (5, "rotation", "LINEAR", JOINT1_ROT_TIMES, JOINT1_ROT),
        (4, "translation", "STEP", JOINT0_T_TIMES, JOINT0_T),
    ],
]

TRIANGLE = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
TRIANGLE_N = np.array([[0, 0, 1], [0, 0.6, 0.8], [0.6, 0, 0.8]], float)
QUAD = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float)
QUAD_N = np.array([[0, 0, 1]] * 4, float)
TARGET0_P = np.array([[0, 0, 0.5], [0.1, 0, 0], [0, 0, -0.5], [0.2, 0.3, 0.4]], float)
TARGET0_N = np.array([[0.3, 0, 0], [0, 0.3, 0], [0, 0, 0], [-0.2, 0, 0]], float)
TARGET1_P = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], float)
MESH_WEIGHTS = [0.2, 0.1]
# The skinned strip: 5 columns along x at y = -0.2 and 0.2.
STRIP = np.array([[x, y, 0.0] for x in (0.0, 0.5, 1.0, 1.5, 2.0) for y in (-0.2, 0.2)])
STRIP_N = np.array([[0.0, 0.0, 1.0]] * len(STRIP))
# JOINTS_1 / WEIGHTS_1 (normalized unsigned bytes) and JOINTS_0 / WEIGHTS_0 (float), with
# every vertex's weights summing to 1 (to float rounding).
WEIGHTS1_U8 = np.array(
    [
        [51, 0, 0, 0],
        [0, 0, 0, 0],
        [102, 25, 0, 0],
        [0, 0, 0, 0],
        [51, 51, 0, 0],
        [255, 0, 0, 0],
        [0, 0, 0, 0],
        [26, 0, 0, 0],
        [0, 0, 0, 0],
        [77, 0, 0, 0],
    ],
    np.uint8,
)
JOINTS1 = np.array(
    [
        [2, 0, 0, 0],
        [0, 0, 0, 0],
        [2, 1, 0, 0],
        [0, 0, 0, 0],
        [0, 2, 0, 0],
        [1, 0, 0, 0],
        [0, 0, 0, 0],
        [0, 0, 0, 0],
        [0, 0, 0, 0],
        [2, 0, 0, 0],
    ],
    np.uint16,
)


def strip_influences():
    joints0, weights0 = [], []
    for i, (x, _) in enumerate(STRIP[:, :2]):
        rest = 1.0 - WEIGHTS1_U8[i].astype(float).sum() / 255.0
        # Joint 0 covers x in [0, 1], joint 1 beyond, blended in between.
        a = np.clip(1.0 - x / 2.0, 0, 1)
        joints0.append([0, 1, 2, 0])
        weights0.append([rest * a, rest * (1 - a) * 0.7, rest * (1 - a) * 0.3, 0.0])
    return np.array(joints0, np.uint8), f32(weights0)


def quat_matrix(q) -> np.ndarray:
    x, y, z, w = np.asarray(q, float) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def trs(translation=(0, 0, 0), rotation=(0, 0, 0, 1), scale=(1, 1, 1)) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = quat_matrix(rotation) @ np.diag(scale)
    m[:3, 3] = translation
    return m


def bind_globals() -> dict[int, np.ndarray]:
    """Joint world matrices at rest (no animation): the bind pose the inverse bind matrices
    invert."""
    return world_matrices({})


def build_scene(path: Path) -> dict:
    b = GltfBuilder()
    tri_p = b.add(TRIANGLE, 5126, "VEC3")
    tri_n = b.add(TRIANGLE_N, 5126, "VEC3")
    quad_p = b.add(QUAD, 5126, "VEC3")
    quad_n = b.add(QUAD_N, 5126, "VEC3")
    t0p = b.add(TARGET0_P, 5126, "VEC3")
    t0n = b.add(TARGET0_N, 5126, "VEC3")
    t1p = b.add(TARGET1_P, 5126, "VEC3")
    quad_i = b.add([0, 1, 2, 0, 2, 3], 5123, "SCALAR")
    strip_p = b.add(STRIP, 5126, "VEC3")
    strip_n = b.add(STRIP_N, 5126, "VEC3")
    joints0, weights0 = strip_influences()
    j0 = b.add(joints0, 5121, "VEC4")
    w0 = b.add(weights0, 5126, "VEC4")
    j1 = b.add(JOINTS1, 5123, "VEC4")
    w1 = b.add(WEIGHTS1_U8, 5121, "VEC4", normalized=True)
    strip_i = []
    for c in range(4):
        a = 2 * c
        strip_i += [a, a + 2, a + 3, a, a + 3, a + 1]
    strip_idx = b.add(strip_i, 5123, "SCALAR")
    bind = bind_globals()
    ibm = np.stack([np.linalg.inv(bind[j]).T.reshape(16) for j in (4, 5, 6)])  # column-major
    ibm_acc = b.add(ibm, 5126, "MAT4")

    animations = []
    for channels in ANIMATIONS:
        samplers, chans = [], []
        for node, target, interp, times, outputs in channels:
            inp = b.add(times, 5126, "SCALAR")
            out = np.asarray(outputs, float)
            out_type = {
                "translation": "VEC3",
                "scale": "VEC3",
                "rotation": "VEC4",
                "weights": "SCALAR",
            }[target]
            width = {"VEC3": 3, "VEC4": 4, "SCALAR": 1}[out_type]
            outp = b.add(out.reshape(-1, width), 5126, out_type)
            chans.append({"sampler": len(samplers), "target": {"node": node, "path": target}})
            samplers.append({"input": inp, "output": outp, "interpolation": interp})
        animations.append({"channels": chans, "samplers": samplers})

    nodes = []
    for i in range(8):
        node = {k: list(map(float, v)) for k, v in NODE_TRS[i].items()}
        nodes.append(node)
    nodes[0]["children"] = [1, 7]
    nodes[4]["children"] = [5]
    nodes[5]["children"] = [6]
    nodes[1]["mesh"] = 0
    nodes[2]["mesh"] = 1
    nodes[3]["mesh"] = 2
    nodes[3]["skin"] = 0
    nodes[7]["camera"] = 0
    doc = {
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0, 2, 3, 4]}],
        "nodes": nodes,
        "cameras": [{"type": "perspective", "perspective": {"yfov": 0.8, "znear": 0.01}}],
        "meshes": [
            {"primitives": [{"attributes": {"POSITION": tri_p, "NORMAL": tri_n}}]},
            {
                "primitives": [
                    {
                        "attributes": {"POSITION": quad_p, "NORMAL": quad_n},
                        "indices": quad_i,
                        "targets": [{"POSITION": t0p, "NORMAL": t0n}, {"POSITION": t1p}],
                    }
                ],
                "weights": MESH_WEIGHTS,
            },
            {
                "primitives": [
                    {
                        "attributes": {
                            "POSITION": strip_p,
                            "NORMAL": strip_n,
                            "JOINTS_0": j0,
                            "WEIGHTS_0": w0,
                            "JOINTS_1": j1,
                            "WEIGHTS_1": w1,
                        },
                        "indices": strip_idx,
                    }
                ]
            },
        ],
        "skins": [{"joints": [4, 5, 6], "inverseBindMatrices": ibm_acc, "skeleton": 4}],
        "animations": animations,
        **b.buffers(),
    }
    path.write_text(json.dumps(doc))
    return doc


# ---- The reference: glTF 2.0's formulas.


def slerp(a: np.ndarray, b: np.ndarray, s: float) -> np.ndarray:
    """Appendix C's slerp: the shorter arc, normalized lerp for nearly equal rotations."""
    d = float(np.dot(a, b))
    if d < 0:
        b, d = -b, -d
    if d > 0.9995:
        r = (1 - s) * a + s * b
        return r / np.linalg.norm(r)
    theta0 = np.arccos(d)
    theta = s * theta0
    r = (np.cos(theta) - d * np.sin(theta) / np.sin(theta0)) * a + np.sin(theta) / np.sin(
        theta0
    ) * b
    return r / np.linalg.norm(r)


def sample(interp: str, times, outputs, t: float, rotation: bool) -> np.ndarray:
    times = f32(times)
    out = f32(outputs)
    n = len(times)
    if interp == "CUBICSPLINE":
        out = out.reshape(n, 3, -1)
        values = out[:, 1]
    else:
        values = out.reshape(n, -1)
    if rotation:
        values = values / np.linalg.norm(values, axis=1, keepdims=True)
    if t <= times[0]:
        return values[0]
    if t >= times[-1]:
        return values[-1]
    k = int(np.searchsorted(times, t, side="right")) - 1
    td = times[k + 1] - times[k]
    s = (t - times[k]) / td
    if interp == "STEP":
        return values[k]
    if interp == "LINEAR":
        if rotation:
            return slerp(values[k], values[k + 1], s)
        return (1 - s) * values[k] + s * values[k + 1]
    vk, bk, ak1, vk1 = out[k, 1], out[k, 2], out[k + 1, 0], out[k + 1, 1]
    p = (
        (2 * s**3 - 3 * s**2 + 1) * vk
        + td * (s**3 - 2 * s**2 + s) * bk
        + (-2 * s**3 + 3 * s**2) * vk1
        + td * (s**3 - s**2) * ak1
    )
    if rotation:
        p = p / np.linalg.norm(p)
    return p


def pose_at(t: float | None, animations: list[int] | None = None) -> dict:
    """(node, path) -> value at t of the chosen animations (all: None)."""
    if t is None:
        return {}
    chosen = range(len(ANIMATIONS)) if animations is None else animations
    pose = {}
    for a in chosen:
        for node, target, interp, times, outputs in ANIMATIONS[a]:
            pose[(node, target)] = sample(interp, times, outputs, t, target == "rotation")
    return pose


def world_matrices(pose: dict) -> dict[int, np.ndarray]:
    def local(i):
        own = NODE_TRS[i]
        tr = pose.get((i, "translation"), np.asarray(own.get("translation", [0, 0, 0]), float))
        rot = pose.get((i, "rotation"), np.asarray(own.get("rotation", [0, 0, 0, 1]), float))
        sc = pose.get((i, "scale"), np.asarray(own.get("scale", [1, 1, 1]), float))
        return trs(tr, rot, sc)

    out = {}

    def world(i):
        if i not in out:
            out[i] = (world(PARENTS[i]) if i in PARENTS else np.eye(4)) @ local(i)
        return out[i]

    for i in NODE_TRS:
        world(i)
    return out


def transform(m: np.ndarray, p: np.ndarray, n: np.ndarray):
    pos = (m[:3, :3] @ p.T).T + m[:3, 3]
    nm = np.linalg.inv(m[:3, :3]).T
    nor = (nm @ n.T).T
    return pos, nor / np.linalg.norm(nor, axis=1, keepdims=True)


def reference(doc: dict, t: float | None, animations: list[int] | None = None) -> dict:
    pose = pose_at(t, animations)
    worlds = world_matrices(pose)
    # Mesh 0 on node 1.
    tri = transform(worlds[1], f32(TRIANGLE), f32(TRIANGLE_N))
    # Mesh 1 on node 2: morphed, then placed by the node.
    w = pose.get((2, "weights"), np.asarray(MESH_WEIGHTS, float))
    p = f32(QUAD) + w[0] * f32(TARGET0_P) + w[1] * f32(TARGET1_P)
    n = f32(QUAD_N) + w[0] * f32(TARGET0_N)
    quad = transform(worlds[2], p, n)
    # Mesh 2 skinned by joints 4, 5, 6 (node 3's own transform ignored).
    ibm = f32(np.stack([np.linalg.inv(bind_globals()[j]).T.reshape(16) for j in (4, 5, 6)]))
    joint_m = [worlds[j] @ ibm[k].reshape(4, 4).T for k, j in enumerate((4, 5, 6))]
    joints0, weights0 = strip_influences()
    positions, normals = [], []
    for v in range(len(STRIP)):
        m = np.zeros((4, 4))
        for joints, weights in (
            (joints0[v], weights0[v]),
            (JOINTS1[v], WEIGHTS1_U8[v].astype(float) / 255.0),
        ):
            for j, wt in zip(joints, weights, strict=True):
                m += wt * joint_m[int(j)]
        pos, nor = transform(m, f32(STRIP[v : v + 1]), f32(STRIP_N[v : v + 1]))
        positions.append(pos[0])
        normals.append(nor[0])
    strip = (np.array(positions), np.array(normals))
    cam = worlds[7]
    forward = cam[:3, :3] @ np.array([0, 0, -1.0])
    return {
        "worlds": worlds,
        "meshes": {1: tri, 2: quad, 3: strip},
        "morphed": bool(np.any(w != 0)),
        "camera": (cam[:3, 3], forward / np.linalg.norm(forward)),
    }


# ---- The worker.


def pose(worker: str, scene: Path, *args: str) -> dict:
    proc = subprocess.run(
        [worker, "pose", str(scene), *args, "--json"], capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    out = json.loads(proc.stdout)
    assert out["ok"], out
    return out


def column_major(m) -> np.ndarray:
    return np.asarray(m, float).reshape(4, 4).T


def compare(got: dict, want: dict) -> None:
    nodes = {n["index"]: column_major(n["world"]) for n in got["nodes"]}
    for i, m in want["worlds"].items():
        np.testing.assert_allclose(nodes[i], m, rtol=RTOL, atol=ATOL, err_msg=f"node {i}")
    positions = np.asarray(got["world"]["positions"], float)
    normals = np.asarray(got["world"]["normals"], float)
    ranges = {r["node"]: r for r in got["ranges"]}
    assert set(ranges) == {1, 2, 3}
    assert ranges[3]["skinned"]
    assert ranges[2]["morphed"] == want["morphed"]
    for node, (p, n) in want["meshes"].items():
        r = ranges[node]
        assert r["instance"] is None, "a mesh used once is flattened"
        assert r["count"] == len(p)
        sl = slice(r["first_vertex"], r["first_vertex"] + r["count"])
        np.testing.assert_allclose(positions[sl], p, rtol=RTOL, atol=ATOL, err_msg=f"node {node}")
        np.testing.assert_allclose(normals[sl], n, rtol=RTOL, atol=ATOL, err_msg=f"node {node}")
    assert got["camera"]["node"] == 7
    np.testing.assert_allclose(got["camera"]["position"], want["camera"][0], rtol=RTOL, atol=ATOL)
    np.testing.assert_allclose(got["camera"]["forward"], want["camera"][1], rtol=RTOL, atol=ATOL)


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> tuple[Path, dict]:
    path = tmp_path_factory.mktemp("anim") / "animated.gltf"
    return path, build_scene(path)


# Before every first key, between keys, exactly on keys (1.0: translation; 1.5: rotation;
# 2.0: scale, weights and the joint's rotation), after every last key.
@pytest.mark.parametrize("t", [-0.5, 0.25, 0.8, 1.0, 1.5, 1.7, 2.0, 2.2, 2.9, 4.0])
def test_the_pose_at_a_time_matches_the_specification(worker_binary, scene, t):
    path, doc = scene
    got = pose(worker_binary, path, "--time", repr(t))
    assert got["time"] == t
    compare(got, reference(doc, t))


def test_without_a_time_the_nodes_keep_their_own_transforms(worker_binary, scene):
    path, doc = scene
    got = pose(worker_binary, path)
    assert got["time"] is None
    compare(got, reference(doc, None))


def test_only_the_chosen_animation_drives_the_pose(worker_binary, scene):
    path, doc = scene
    compare(
        pose(worker_binary, path, "--time", "1.7", "--animation", "1"), reference(doc, 1.7, [1])
    )
    compare(
        pose(worker_binary, path, "--time", "1.7", "--animation", "0"), reference(doc, 1.7, [0])
    )


def test_the_reference_sees_the_shorter_arc(scene):
    """The parent's second rotation interval has keys with a negative dot product: the
    reference (and the worker, compared above) take the negated key's shorter arc."""
    q1, q2 = PARENT_ROT[1], PARENT_ROT[2]
    assert np.dot(q1, q2) < 0
    mid = sample("LINEAR", PARENT_ROT_TIMES, PARENT_ROT, 2.0, True)
    # Half way along the shorter arc: the angle to either key is half the angle between them.
    half = np.arccos(abs(np.dot(q1, q2)))
    assert np.isclose(np.arccos(abs(np.dot(mid, q1))), half / 2)
    assert np.isclose(np.arccos(abs(np.dot(mid, q2))), half / 2)


def test_bad_keyframe_times_are_refused_naming_the_sampler(worker_binary, tmp_path, scene):
    _, doc = scene
    bad = json.loads(json.dumps(doc))
    # Sampler 0 of animation 0 gets keyframe times that do not strictly increase.
    b = GltfBuilder()
    b.data = bytearray(base64.b64decode(bad["buffers"][0]["uri"].split(",", 1)[1]))
    b.views, b.accessors = bad["bufferViews"], bad["accessors"]
    bad["animations"][0]["samplers"][0]["input"] = b.add([0.5, 0.5, 2.5], 5126, "SCALAR")
    bad.update(b.buffers())
    path = tmp_path / "bad.gltf"
    path.write_text(json.dumps(bad))
    proc = subprocess.run(
        [worker_binary, "pose", str(path), "--time", "1", "--json"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 1
    out = json.loads(proc.stdout)
    assert out["ok"] is False
    assert out["path"] == "animations[0].samplers[0].input"


# ---- Rendering at a time.


def render_scene(path: Path) -> None:
    """An emissive quad that an animation moves across the camera's view (x from -1 to 1
    over t in [0, 1])."""
    b = GltfBuilder()
    p = b.add([[-0.3, -0.3, 0], [0.3, -0.3, 0], [0.3, 0.3, 0], [-0.3, 0.3, 0]], 5126, "VEC3")
    i = b.add([0, 1, 2, 0, 2, 3], 5123, "SCALAR")
    times = b.add([0.0, 1.0], 5126, "SCALAR")
    moves = b.add([[-1.0, 0, 0], [1.0, 0, 0]], 5126, "VEC3")
    doc = {
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0, 1]}],
        "nodes": [{"mesh": 0}, {"camera": 0, "translation": [0, 0, 3]}],
        "cameras": [{"type": "perspective", "perspective": {"yfov": 1.0, "znear": 0.01}}],
        "materials": [
            {"emissiveFactor": [1, 1, 1], "pbrMetallicRoughness": {"baseColorFactor": [0, 0, 0, 1]}}
        ],
        "meshes": [{"primitives": [{"attributes": {"POSITION": p}, "indices": i, "material": 0}]}],
        "animations": [
            {
                "channels": [{"sampler": 0, "target": {"node": 0, "path": "translation"}}],
                "samplers": [{"input": times, "output": moves}],
            }
        ],
        **b.buffers(),
    }
    path.write_text(json.dumps(doc))


def render(worker: str, scene: Path, out: Path, t: str) -> np.ndarray:
    proc = subprocess.run(
        [
            worker,
            "render",
            str(scene),
            "-o",
            str(out),
            "--spp",
            "4",
            "--width",
            "32",
            "--height",
            "24",
            "--threads",
            "1",
            "--seed",
            "3",
            "--time",
            t,
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    channels = read_exr(str(out))
    return np.stack([channels["R"], channels["G"], channels["B"]], -1)


def test_a_frame_renders_at_its_time(worker_binary, tmp_path):
    scene_path = tmp_path / "moving.gltf"
    render_scene(scene_path)
    a = render(worker_binary, scene_path, tmp_path / "a.exr", "0")
    b = render(worker_binary, scene_path, tmp_path / "b.exr", "1")
    a2 = render(worker_binary, scene_path, tmp_path / "a2.exr", "0")
    assert a.max() > 0.5 and b.max() > 0.5
    assert np.array_equal(a, a2), "the same time renders the same image"
    assert not np.array_equal(a, b)
    # The quad is left of centre at t = 0 and right of it at t = 1.
    half = a.shape[1] // 2
    assert a[:, :half].sum() > 10 * a[:, half:].sum()
    assert b[:, half:].sum() > 10 * b[:, :half].sum()
