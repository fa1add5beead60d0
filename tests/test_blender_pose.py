"""Animated frames where Blender put them: a shot exported by the Blender add-on (a camera
dollying under a Track To constraint, a box turning under a turning parent, a cylinder skinned
to two bones, Bezier-eased; tests/blender_pose_driver.py) is posed by the worker at the farm's
time of frame f (f / fps, domain/frames.py) exactly where Blender's own evaluation of frame f
puts it: the camera's position and axes, the box's world matrix and every skinned vertex, to
float precision. No render: the pose is compared directly (`renderfarm-worker pose`)."""

from __future__ import annotations

import json
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest

from renderfarm.domain.frames import frame_time

from .test_blender_addon import blender_python

DRIVER = Path(__file__).with_name("blender_pose_driver.py")
# Blender's Z-up world to glTF's Y-up: (x, y, z) -> (x, z, -y).
Z_TO_Y = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])


def run_driver(out: Path, *args: str) -> dict:
    proc = subprocess.run(
        [blender_python(), str(DRIVER), str(out), *args],
        capture_output=True,
        text=True,
        timeout=300,
        env={"BLENDER_USER_RESOURCES": str(out / "blender-user"), "PATH": "/usr/bin:/bin"},
    )
    lines = [line for line in proc.stdout.splitlines() if line.startswith("RESULT ")]
    assert proc.returncode == 0 and lines, proc.stdout[-2000:] + proc.stderr[-4000:]
    return json.loads(lines[-1][len("RESULT ") :])


@pytest.fixture(scope="module")
def shot(tmp_path_factory) -> dict:
    return run_driver(tmp_path_factory.mktemp("pose"))


def node_names(glb: Path) -> list[str]:
    data = glb.read_bytes()
    (length,) = struct.unpack_from("<I", data, 12)
    return [n.get("name", "") for n in json.loads(data[20 : 20 + length])["nodes"]]


def posed(worker_binary: str, glb: str, t: float) -> dict:
    proc = subprocess.run(
        [worker_binary, "pose", glb, "--time", repr(t), "--json"],
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    return json.loads(proc.stdout)


def nearest(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """For each point of a, its distance to the nearest point of b."""
    return np.sqrt(((a[:, None, :] - b[None, :, :]) ** 2).sum(-1)).min(1)


def test_frames_pose_camera_node_and_skin_where_blender_does(worker_binary, shot):
    names = node_names(Path(shot["glb"]))
    fps = shot["fps"]
    assert fps == 24.0
    for frame, blender in shot["frames"].items():
        pose = posed(worker_binary, shot["glb"], frame_time(int(frame), fps))
        # The camera: Blender's camera looks down its local -Z with +Y up, as glTF's does.
        camera = np.array(blender["camera"])
        assert np.abs(np.array(pose["camera"]["position"]) - Z_TO_Y @ camera[:3, 3]).max() < 1e-5
        assert np.abs(np.array(pose["camera"]["forward"]) + Z_TO_Y @ camera[:3, 2]).max() < 1e-5
        assert np.abs(np.array(pose["camera"]["up"]) - Z_TO_Y @ camera[:3, 1]).max() < 1e-5
        # The box: its world matrix, axes and position, in glTF's frame.
        box = np.array(pose["nodes"][names.index("Box")]["world"]).reshape(4, 4).T
        want = np.array(blender["box"])
        want_gltf = Z_TO_Y @ want[:3, :3] @ Z_TO_Y.T
        assert np.abs(box[:3, :3] - want_gltf).max() < 1e-5, frame
        assert np.abs(box[:3, 3] - Z_TO_Y @ want[:3, 3]).max() < 1e-5, frame
        # The skinned cylinder: every vertex where Blender's deformation puts it (the .glb
        # splits vertices along seams, so match each to its nearest, both ways).
        tube = [r for r in pose["ranges"] if names[r["node"]] == "Tube"]
        assert len(tube) == 1 and tube[0]["skinned"]
        positions = np.array(pose["world"]["positions"]).reshape(-1, 3)
        first, count = tube[0]["first_vertex"], tube[0]["count"]
        ours = positions[first : first + count]
        theirs = np.array(blender["tube"]) @ Z_TO_Y.T
        assert nearest(ours, theirs).max() < 1e-5, frame
        assert nearest(theirs, ours).max() < 1e-5, frame
    # The shot moves: the frames are not all one pose.
    first, last = shot["frames"]["1"], shot["frames"]["48"]
    assert np.abs(np.array(first["box"]) - np.array(last["box"])).max() > 0.5


def test_a_scene_the_exporter_fails_on_is_exported_without_pointer_animation(
    worker_binary, tmp_path
):
    """Blender 5.0's exporter fails writing the material animation of a mesh with a modifier
    and a material; the add-on exports it again without KHR_animation_pointer and says so, and
    the node animation still reaches the farm."""
    result = run_driver(tmp_path, "--fallback")
    assert len(result["notes"]) == 1
    assert "material, light and camera animation" in result["notes"][0]
    data = Path(result["glb"]).read_bytes()
    (length,) = struct.unpack_from("<I", data, 12)
    doc = json.loads(data[20 : 20 + length])
    paths = [c["target"]["path"] for a in doc["animations"] for c in a["channels"]]
    assert "translation" in paths and "pointer" not in paths
    names = [n.get("name", "") for n in doc["nodes"]]
    early, late = (posed(worker_binary, result["glb"], f / 24.0) for f in (1, 48))
    cube = names.index("Cube")
    assert early["nodes"][cube]["world"][12] == pytest.approx(0.0, abs=1e-6)
    assert late["nodes"][cube]["world"][12] == pytest.approx(1.0, abs=1e-6)
