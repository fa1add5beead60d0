"""Runs inside Blender's Python (the bpy module of .venv-blender), started by
tests/test_blender_pose.py: builds an animated shot, exports it with the add-on's own export
(renderfarm_blender/export.py, imported from the source tree: no farm, no installation), and
prints, as one JSON line `RESULT {...}`, where Blender puts everything at each frame.

    python tests/blender_pose_driver.py OUT_DIR [--fallback]

The shot, 48 frames at 24 fps with Blender's default Bezier easing: a camera dollying in, aimed
by a Track To constraint at an empty; a box turning and sliding under a parent empty that
turns too; a cylinder skinned to a two-bone armature whose upper bone bends.
"""

from __future__ import annotations

import json
import math
import os
import sys

import bpy

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "integrations", "blender"))
from renderfarm_blender import export  # noqa: E402

OUT = sys.argv[1]  # then --fallback: the scene the exporter fails on (fallback())
FRAMES = (1, 12, 24, 36, 48)


def keyed(obj, path: str, first, last) -> None:
    setattr(obj, path, first)
    obj.keyframe_insert(path, frame=1)
    setattr(obj, path, last)
    obj.keyframe_insert(path, frame=48)


def build():
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.fps, scene.render.fps_base = 24, 1.0
    scene.frame_start, scene.frame_end = 1, 48

    bpy.ops.object.empty_add(location=(0.5, 0, 0))
    pivot = bpy.context.object
    pivot.name = "Pivot"
    keyed(pivot, "rotation_euler", (0, 0, 0), (0, 0, math.radians(40)))
    bpy.ops.mesh.primitive_cube_add(size=1.0, location=(0, 0, 0.5))
    box = bpy.context.object
    box.name = "Box"
    box.parent = pivot
    keyed(box, "rotation_euler", (0, 0, 0), (math.radians(20), 0, math.pi))
    keyed(box, "location", (0, 0, 0.5), (1.5, 0.5, 0.8))

    bpy.ops.object.armature_add(location=(-2, 0, 0))
    rig = bpy.context.object
    rig.name = "Rig"
    bpy.ops.object.mode_set(mode="EDIT")
    lower = rig.data.edit_bones[0]
    lower.name = "Lower"
    lower.head, lower.tail = (0, 0, 0), (0, 0, 1)
    upper = rig.data.edit_bones.new("Upper")
    upper.head, upper.tail = (0, 0, 1), (0, 0, 2)
    upper.parent = lower
    bpy.ops.object.mode_set(mode="OBJECT")
    bpy.ops.mesh.primitive_cylinder_add(radius=0.2, depth=2, location=(-2, 0, 1), vertices=12)
    tube = bpy.context.object
    tube.name = "Tube"
    bpy.ops.object.mode_set(mode="EDIT")
    bpy.ops.mesh.subdivide(number_cuts=6)
    bpy.ops.object.mode_set(mode="OBJECT")
    tube.select_set(True)
    rig.select_set(True)
    bpy.context.view_layer.objects.active = rig
    bpy.ops.object.parent_set(type="ARMATURE_AUTO")
    bend = rig.pose.bones["Upper"]
    bend.rotation_mode = "XYZ"
    keyed(bend, "rotation_euler", (0, 0, 0), (math.radians(70), 0, math.radians(30)))

    bpy.ops.object.empty_add(location=(0, 0, 0.7))
    aim = bpy.context.object
    aim.name = "Aim"
    bpy.ops.object.camera_add(location=(0, -8, 3))
    cam = bpy.context.object
    cam.name = "Cam"
    track = cam.constraints.new("TRACK_TO")
    track.target = aim
    keyed(cam, "location", (0, -8, 3), (1, -4.5, 2))
    scene.camera = cam
    return scene, box, tube, cam


def main() -> dict:
    scene, box, tube, cam = build()
    glb = export.export_animation(scene)
    path = os.path.join(OUT, "shot.glb")
    with open(path, "wb") as f:
        f.write(glb)
    frames = {}
    for frame in FRAMES:
        scene.frame_set(frame)
        depsgraph = bpy.context.evaluated_depsgraph_get()
        evaluated = tube.evaluated_get(depsgraph)
        mesh = evaluated.to_mesh()
        tube_world = [list(evaluated.matrix_world @ v.co) for v in mesh.vertices]
        evaluated.to_mesh_clear()
        frames[frame] = {
            "box": [list(row) for row in box.matrix_world],
            "camera": [list(row) for row in cam.matrix_world],
            "tube": tube_world,
        }
    return {"glb": path, "fps": export.exporter_fps(scene), "frames": frames}


def fallback() -> dict:
    """A subdivided cube with a material, moving: Blender 5.0's exporter fails on its material
    animation, and the add-on exports it again without KHR_animation_pointer, saying so."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, 48
    bpy.ops.mesh.primitive_cube_add()
    cube = bpy.context.object
    cube.modifiers.new("Subdivision", "SUBSURF")
    material = bpy.data.materials.new("Paint")
    material.use_nodes = True
    cube.data.materials.append(material)
    keyed(cube, "location", (0, 0, 0), (1, 0, 0))
    bpy.ops.object.camera_add(location=(0, -6, 2), rotation=(1.2, 0, 0))
    scene.camera = bpy.context.object
    glb, notes = export.export_animation_reporting(scene)
    path = os.path.join(OUT, "fallback.glb")
    with open(path, "wb") as f:
        f.write(glb)
    return {"glb": path, "notes": notes}


if __name__ == "__main__":
    result = fallback() if "--fallback" in sys.argv else main()
    print("RESULT " + json.dumps(result), flush=True)
