"""Runs inside Blender's Python (the bpy module of .venv-blender), started by
tests/test_compressed_meshes.py: builds a small scene (a smooth UV sphere on a ground plane, a
point light, a camera) and exports it with Blender's own glTF exporter twice, as plain.glb and
with Draco mesh compression (KHR_draco_mesh_compression, the exporter's default quantization)
as draco.glb, into the directory given.

    python tests/blender_export.py OUT_DIR
"""

from __future__ import annotations

import os
import sys

out_dir = sys.argv[1]
# Blender's user resources in the test's directory, never the user's own (read at import).
os.environ["BLENDER_USER_RESOURCES"] = os.path.join(out_dir, "blender-user")

import bpy  # noqa: E402
from mathutils import Vector  # noqa: E402

for obj in list(bpy.data.objects):
    bpy.data.objects.remove(obj)
scene = bpy.context.scene
scene.world = None


def material(name: str, color):
    mat = bpy.data.materials.new(name)
    bsdf = mat.node_tree.nodes.get("Principled BSDF")
    bsdf.inputs["Base Color"].default_value = (*color, 1.0)
    bsdf.inputs["Roughness"].default_value = 0.6
    return mat


bpy.ops.mesh.primitive_plane_add(size=6.0, location=(0, 0, 0))
bpy.context.active_object.data.materials.append(material("Ground", (0.7, 0.7, 0.7)))
bpy.ops.mesh.primitive_uv_sphere_add(segments=48, ring_count=24, radius=1.0, location=(0, 0, 1))
sphere = bpy.context.active_object
bpy.ops.object.shade_smooth()
sphere.data.materials.append(material("Ball", (0.8, 0.3, 0.1)))
light = bpy.data.objects.new("Lamp", bpy.data.lights.new("Lamp", "POINT"))
light.data.energy = 800.0
light.data.shadow_soft_size = 0.0
light.location = (2.5, -2.0, 4.0)
scene.collection.objects.link(light)
cam = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
scene.collection.objects.link(cam)
cam.location = (4.0, -4.5, 3.0)
cam.rotation_euler = (Vector((0, 0, 0.8)) - cam.location).to_track_quat("-Z", "Y").to_euler()
scene.camera = cam

for name, draco in (("plain", False), ("draco", True)):
    result = bpy.ops.export_scene.gltf(
        filepath=os.path.join(out_dir, f"{name}.glb"),
        export_format="GLB",
        export_cameras=True,
        export_lights=True,
        export_draco_mesh_compression_enable=draco,
    )
    assert result == {"FINISHED"}, result
print("EXPORTED", flush=True)
