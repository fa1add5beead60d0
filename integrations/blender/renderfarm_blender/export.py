"""The scene as a .glb for the farm, written by Blender's own glTF exporter."""

from __future__ import annotations

import json
import os
import shutil
import struct
import tempfile

import bpy

# The exporter's options for a render: what Blender renders (objects enabled for rendering,
# modifiers and geometry-nodes instances applied) as it is at the frame being exported,
# cameras and lights included, no animation (the farm renders still frames). Lights are
# written with the exporter's "COMPAT" unit conversion (a point light of P W becomes an
# intensity of P / 4 pi, a sun keeps its W/m^2), the radiometric units the farm renders with,
# so lights keep the ratio to emissive materials they have in Cycles; the "SPEC" default would
# multiply them by 683 lm/W.
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


class ExportError(RuntimeError):
    pass


def frames_to_submit(scene) -> list[int]:
    """The frames a submission renders: the scene's current frame. The farm renders still
    images; a frame range would be a list of frames here, one job each."""
    return [scene.frame_current]


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


def export_frame(scene, frame: int) -> bytes:
    """The scene at `frame` as .glb bytes, through the active camera."""
    if scene.camera is None:
        raise ExportError(f"scene '{scene.name}' has no active camera")
    directory = tempfile.mkdtemp(prefix="renderfarm-")
    path = os.path.join(directory, "scene.glb")
    previous = scene.frame_current, scene.frame_subframe
    try:
        if frame != scene.frame_current:
            scene.frame_set(frame)
        result = bpy.ops.export_scene.gltf(filepath=path, **EXPORT_OPTIONS)
        if "FINISHED" not in result or not os.path.exists(path):
            raise ExportError("Blender's glTF exporter did not write the scene")
        with open(path, "rb") as f:
            glb = f.read()
    finally:
        if (scene.frame_current, scene.frame_subframe) != previous:
            scene.frame_set(previous[0], subframe=previous[1])
        shutil.rmtree(directory, ignore_errors=True)
    return keep_only_camera(glb, scene.camera.name)
