"""The scene as a .glb for the farm, written by Blender's own glTF exporter."""

from __future__ import annotations

import json
import os
import shutil
import struct
import tempfile

import bpy

# The exporter's options for a still: what Blender renders (objects enabled for rendering,
# modifiers and geometry-nodes instances applied) as it is at the frame being exported,
# cameras and lights included, no animation. Lights are written with the exporter's "COMPAT"
# unit conversion (a point light of P W becomes an intensity of P / 4 pi, a sun keeps its
# W/m^2), the radiometric units the farm renders with, so lights keep the ratio to emissive
# materials they have in Cycles; the "SPEC" default would multiply them by 683 lm/W.
EXPORT_OPTIONS = {
    "export_format": "GLB",
    "use_active_scene": True,
    "use_renderable": True,
    "export_apply": True,
    "export_gn_mesh": True,
    "export_cameras": True,
    "export_lights": True,
    "export_import_convert_lighting_mode": "COMPAT",
    "export_animations": False,
    "export_current_frame": True,
    "export_yup": True,
    "export_extras": False,
    "check_existing": False,
}

# The exporter's options for an animation: the same scene, and the scene's timeline baked into
# ONE glTF animation. "SCENE" mode evaluates the whole scene at every frame of
# scene.frame_start..frame_end (scene.frame_set, so constraints, drivers, parenting, rigid
# bodies and armatures are included) and writes every object's local translation, rotation and
# scale, every bone, and the shape-key weights of meshes without modifiers, at glTF time
# frame / fps; with anim_scene_split_object off all of it is one animation named after the
# scene, so the farm's `animation` setting (empty: every animation) plays the scene's timeline
# whole. (The "ACTIONS" default writes each action as its own animation, laid out from its own
# frame range and not baked: two objects' actions would be separate animations, constraints and
# drivers would be lost.) Sampling every frame (frame_step 1) gives keys on exactly the frames
# rendered; constant channels keep two keys (keep_anim_object) rather than falling back to the
# rest transform, which is the scene at frame 0 (export_current_frame off: the rest pose and
# the meshes are taken at frame 0, then the animation is sampled). Material, light and camera
# data animation would need KHR_animation_pointer, which the farm ignores: off (scan.py lists
# it). All bones are written (def_bones off), so a deforming bone's parents keep their motion.
ANIMATION_OPTIONS = {
    **EXPORT_OPTIONS,
    "export_animations": True,
    "export_current_frame": False,
    "export_animation_mode": "SCENE",
    "export_anim_scene_split_object": False,
    "export_force_sampling": True,
    "export_frame_step": 1,
    "export_optimize_animation_size": True,
    "export_optimize_animation_keep_anim_object": True,
    "export_optimize_animation_keep_anim_armature": True,
    "export_anim_slide_to_zero": False,
    "export_def_bones": False,
    "export_morph_animation": True,
    "export_pointer_animation": False,
}


class ExportError(RuntimeError):
    pass


def scene_variants() -> list[str]:
    """The names of the material variants (KHR_materials_variants) Blender's glTF exporter
    writes, in its list's order: those of its list (bpy.data.scenes[0]
    .gltf2_KHR_materials_variants_variants: the exporter reads the first scene's, whichever
    scene it exports) that some mesh maps a material to (gltf2_variant_mesh_data), when its
    Material Variants preference is on (off, it writes none, and the list may not exist)."""
    addon = bpy.context.preferences.addons.get("io_scene_gltf2")
    prefs = getattr(addon, "preferences", None)
    if prefs is None or not getattr(prefs, "KHR_materials_variants_ui", False):
        return []
    scenes = bpy.data.scenes
    listed = getattr(scenes[0], "gltf2_KHR_materials_variants_variants", None) if scenes else None
    if not listed:
        return []
    used = {
        v.variant.variant_idx
        for mesh in bpy.data.meshes
        for mapping in getattr(mesh, "gltf2_variant_mesh_data", ())
        for v in mapping.variants
    }
    return [v.name for v in listed if v.variant_idx in used]


def frames_to_submit(scene) -> list[int]:
    """The frame a still submission renders: the scene's current frame."""
    return [scene.frame_current]


def frame_range(scene) -> tuple[int, int, int]:
    """(first, last, step) of the frames Blender renders for the scene's animation:
    frame_start, frame_start + step, ... up to frame_end (last is the last frame rendered)."""
    first, step = scene.frame_start, max(1, scene.frame_step)
    last = first + (max(first, scene.frame_end) - first) // step * step
    return first, last, step


def farm_frames(first: int, last: int, step: int) -> str:
    """A frame range in the farm's syntax: "a-b", or "a-bxN" for every Nth frame."""
    if first == last:
        return str(first)
    return f"{first}-{last}" + (f"x{step}" if step > 1 else "")


def frame_count(first: int, last: int, step: int) -> int:
    return (last - first) // step + 1


def exporter_fps(scene) -> float:
    """The frame rate of the times Blender's glTF exporter writes: it puts frame f at
    f / (render.fps * render.fps_base) seconds (io_scene_gltf2 5.0, and its importer reads times
    back the same way). Blender plays at fps / fps_base, the same rate whenever fps_base is 1;
    otherwise (29.97 = 30 / 1.001) the farm must still be given the exporter's rate so that
    its frame f is Blender's frame f."""
    return scene.render.fps * scene.render.fps_base


def playback_fps(scene) -> float:
    """The frame rate Blender plays the scene at."""
    return scene.render.fps / scene.render.fps_base


def keep_only_camera(glb: bytes, camera_node_name: str) -> bytes:
    """The .glb with the camera taken off every node but the one named camera_node_name.

    The farm renders through the first perspective camera of the scene's node tree, while
    Blender renders through the scene's active camera: the exporter writes every camera, in
    no particular order, so the others are removed (their nodes stay, as empties)."""
    magic, version, _length = struct.unpack_from("<4sII", glb, 0)
    if magic != b"glTF" or version != 2:
        raise ExportError("the exporter did not write a glTF 2.0 binary")
    chunk_length, chunk_type = struct.unpack_from("<I4s", glb, 12)
    if chunk_type != b"JSON":
        raise ExportError("the exported .glb does not start with its JSON chunk")
    doc = json.loads(glb[20 : 20 + chunk_length])
    rest = glb[20 + chunk_length :]
    found = False
    for node in doc.get("nodes", []):
        if "camera" not in node:
            continue
        if node.get("name") == camera_node_name and not found:
            found = True
        else:
            del node["camera"]
    if not found:
        raise ExportError(
            f"the active camera '{camera_node_name}' was not exported "
            "(is it disabled for rendering?)"
        )
    text = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    text += b" " * (-len(text) % 4)  # chunks are 4-byte aligned; JSON is padded with spaces
    body = struct.pack("<I4s", len(text), b"JSON") + text + rest
    return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body


def _export(scene, options: dict, frame: int | None) -> bytes:
    if scene.camera is None:
        raise ExportError(f"scene '{scene.name}' has no active camera")
    directory = tempfile.mkdtemp(prefix="renderfarm-")
    path = os.path.join(directory, "scene.glb")
    previous = scene.frame_current, scene.frame_subframe
    try:
        if frame is not None and frame != scene.frame_current:
            scene.frame_set(frame)
        try:
            result = bpy.ops.export_scene.gltf(filepath=path, **options)
        except RuntimeError as e:  # the exporter's own error, e.g. a rig it cannot bake
            raise ExportError(f"Blender's glTF exporter failed: {e}") from None
        if "FINISHED" not in result or not os.path.exists(path):
            raise ExportError("Blender's glTF exporter did not write the scene")
        with open(path, "rb") as f:
            glb = f.read()
    finally:
        if (scene.frame_current, scene.frame_subframe) != previous:
            scene.frame_set(previous[0], subframe=previous[1])
        shutil.rmtree(directory, ignore_errors=True)
    return keep_only_camera(glb, scene.camera.name)


def export_frame(scene, frame: int) -> bytes:
    """The scene at `frame` as .glb bytes, through the active camera."""
    return _export(scene, EXPORT_OPTIONS, frame)


def export_animation(scene) -> bytes:
    """The scene with its timeline (frame_start..frame_end) baked into one glTF animation, as
    .glb bytes, through the active camera: frame f of the scene at glTF time
    f / exporter_fps(scene). The current frame is left as it was."""
    return _export(scene, ANIMATION_OPTIONS, None)
