"""The scene as a .glb for the farm, written by Blender's own glTF exporter."""

from __future__ import annotations

import json
import math
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
# the meshes are taken at frame 0, then the animation is sampled). All bones are written
# (def_bones off), so a deforming bone's parents keep their motion.
#
# Data animation is written as KHR_animation_pointer channels (export_pointer_animation, which
# the exporter offers in SCENE mode only), and the farm renders them: in SCENE mode the
# exporter samples, at every frame, every light, camera and material property it wrote at
# frame 0 and keeps the ones that change, whatever changes them (keys, drivers). Camera: lens,
# sensor and angle as perspective/yfov (at the scene's aspect ratio), ortho_scale as
# orthographic/xmag and ymag, clip_start and clip_end as znear and zfar. Lights: energy as
# intensity, color, spot_size as spot/outerConeAngle and spot_blend as spot/innerConeAngle,
# cutoff_distance as range. Materials: the Principled BSDF's Base Color (with Alpha when the
# material blends), Metallic, Roughness, IOR, Transmission, Coat Weight and Roughness, Sheen
# Roughness, Specular IOR Level, Emission Color and Strength (emissiveFactor and
# KHR_materials_emissive_strength), Anisotropic, and Value nodes feeding them. Some of what
# Blender 5.0 writes there is wrong, and fix_pointer_animation() below puts it right. Object
# visibility (hide_render) has no channel: the exporter writes no KHR_node_visibility.
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
    "export_pointer_animation": True,
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


def _read_glb(glb: bytes) -> tuple[dict, bytearray]:
    """(JSON document, BIN chunk data) of a glTF binary."""
    magic, version, _length = struct.unpack_from("<4sII", glb, 0)
    if magic != b"glTF" or version != 2:
        raise ExportError("the exporter did not write a glTF 2.0 binary")
    chunk_length, chunk_type = struct.unpack_from("<I4s", glb, 12)
    if chunk_type != b"JSON":
        raise ExportError("the exported .glb does not start with its JSON chunk")
    doc = json.loads(glb[20 : 20 + chunk_length])
    binary = bytearray()
    at = 20 + chunk_length
    if at + 8 <= len(glb):
        bin_length, bin_type = struct.unpack_from("<I4s", glb, at)
        if bin_type == b"BIN\0":
            binary = bytearray(glb[at + 8 : at + 8 + bin_length])
    return doc, binary


def _write_glb(doc: dict, binary: bytes) -> bytes:
    text = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    text += b" " * (-len(text) % 4)  # chunks are 4-byte aligned; JSON is padded with spaces
    body = struct.pack("<I4s", len(text), b"JSON") + text
    if binary:
        binary = bytes(binary) + b"\0" * (-len(binary) % 4)
        body += struct.pack("<I4s", len(binary), b"BIN\0") + binary
    return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body


def keep_only_camera(glb: bytes, camera_node_name: str, fix=None) -> bytes:
    """The .glb with the camera taken off every node but the one named camera_node_name.

    The farm renders through the first perspective camera of the scene's node tree, while
    Blender renders through the scene's active camera: the exporter writes every camera, in
    no particular order, so the others are removed (their nodes stay, as empties). `fix`, if
    given, is called with the document and its binary data to correct them too."""
    doc, binary = _read_glb(glb)
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
    if fix is not None:
        fix(doc, binary)
    return _write_glb(doc, binary)


# What Blender 5.0's exporter writes wrong in KHR_animation_pointer channels, put right so that
# the farm renders every frame as Blender does (and as the still exported at that frame):
# - a light's animated intensity is Blender's power unconverted, while the file's intensity is
#   converted (COMPAT: a point or spot light's W / 4 pi, times 2^exposure): the keys are
#   multiplied by the light's factor (LIGHT_INTENSITY_FACTOR);
# - spot cones are written as "spot.innerConeAngle" and "spot.outerConeAngle" instead of JSON
#   pointers' "spot/...", and the inner cone's keys are spot_blend's values, not the angle
#   (outer x (1 - blend)): renamed and recomputed, and an inner cone is added where only the
#   outer one is animated (the inner follows it);
# - the coat roughness pointer ends with a space: stripped;
# - specularColorFactor is written with four numbers a key (the colour repeated): three kept;
# - sheenColorFactor (Sheen Tint) is written with one number a key, its red only: the channel is
#   dropped (every frame has the tint as at frame 0; scan.py lists it).
def light_intensity_factor(light, obj=None) -> float:
    """What the exporter multiplies a light's power by for the file's intensity with
    export_import_convert_lighting_mode COMPAT: 1 / 4 pi for a point or spot light (a sun
    keeps its W/m^2), times 2^exposure, times the area of an unnormalized light."""
    factor = 2.0 ** getattr(light, "exposure", 0.0)
    if light.type != "SUN":
        factor /= 4.0 * math.pi
    if not getattr(light, "normalize", True) and obj is not None:
        factor *= light.area(world_matrix=obj.matrix_world)
    return factor


def _accessor_values(doc: dict, binary: bytearray, index: int) -> list[list[float]]:
    a = doc["accessors"][index]
    width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}[a["type"]]
    if a.get("componentType") != 5126 or "sparse" in a:  # the exporter writes plain floats
        raise ExportError("an animation accessor of the export is not plain floats")
    view = doc["bufferViews"][a["bufferView"]]
    stride = view.get("byteStride", 4 * width)
    start = view.get("byteOffset", 0) + a.get("byteOffset", 0)
    return [
        list(struct.unpack_from(f"<{width}f", binary, start + i * stride))
        for i in range(a["count"])
    ]


def _add_accessor(doc: dict, binary: bytearray, values: list[list[float]]) -> int:
    """A new float accessor of `values` (one list a key), appended to the binary data."""
    width = len(values[0])
    binary.extend(b"\0" * (-len(binary) % 4))
    offset = len(binary)
    for v in values:
        binary.extend(struct.pack(f"<{width}f", *v))
    doc["buffers"][0]["byteLength"] = len(binary)
    doc["bufferViews"].append(
        {"buffer": 0, "byteOffset": offset, "byteLength": 4 * width * len(values)}
    )
    doc["accessors"].append(
        {
            "bufferView": len(doc["bufferViews"]) - 1,
            "componentType": 5126,
            "count": len(values),
            "type": {1: "SCALAR", 2: "VEC2", 3: "VEC3", 4: "VEC4"}[width],
        }
    )
    return len(doc["accessors"]) - 1


def fix_pointer_animation(doc: dict, binary: bytearray, intensity_factors: dict) -> None:
    """Puts right what the exporter writes wrong in KHR_animation_pointer channels (above).
    intensity_factors: light name -> light_intensity_factor()."""
    lights = doc.get("extensions", {}).get("KHR_lights_punctual", {}).get("lights", [])
    for anim in doc.get("animations", []):
        samplers = anim["samplers"]
        cones: dict[int, dict[str, dict]] = {}
        kept = []
        for ch in anim["channels"]:
            ext = ch["target"].get("extensions", {}).get("KHR_animation_pointer")
            if ch["target"].get("path") != "pointer" or ext is None:
                kept.append(ch)
                continue
            pointer = ext["pointer"].strip().replace("/spot.", "/spot/")
            ext["pointer"] = pointer
            sampler = samplers[ch["sampler"]]
            parts = pointer.split("/")
            if pointer.endswith("/KHR_materials_sheen/sheenColorFactor"):
                if doc["accessors"][sampler["output"]]["type"] != "VEC3":
                    continue  # Sheen Tint's red only: dropped
            elif pointer.endswith("/KHR_materials_specular/specularColorFactor"):
                if doc["accessors"][sampler["output"]]["type"] == "VEC4":
                    values = _accessor_values(doc, binary, sampler["output"])
                    sampler["output"] = _add_accessor(doc, binary, [v[:3] for v in values])
            elif parts[:4] == ["", "extensions", "KHR_lights_punctual", "lights"]:
                light = int(parts[4])
                if parts[5:] == ["intensity"]:
                    factor = intensity_factors.get(lights[light].get("name"), 1.0)
                    values = _accessor_values(doc, binary, sampler["output"])
                    sampler["output"] = _add_accessor(
                        doc, binary, [[v[0] * factor] for v in values]
                    )
                elif parts[5:6] == ["spot"]:
                    cones.setdefault(light, {})[parts[6]] = ch
            kept.append(ch)
        for light, cone in cones.items():
            spot = lights[light].get("spot", {})
            static_outer = spot.get("outerConeAngle", math.pi / 4)
            static_inner = spot.get("innerConeAngle", 0.0)
            blend = 1.0 - static_inner / static_outer if static_outer > 0 else 0.0
            outer_ch, inner_ch = cone.get("outerConeAngle"), cone.get("innerConeAngle")
            outer = {}
            if outer_ch is not None:
                s = samplers[outer_ch["sampler"]]
                times = _accessor_values(doc, binary, s["input"])
                values = _accessor_values(doc, binary, s["output"])
                outer = {round(t[0], 6): v[0] for t, v in zip(times, values, strict=True)}
            if inner_ch is not None:  # its keys are spot_blend's
                s = samplers[inner_ch["sampler"]]
                times = _accessor_values(doc, binary, s["input"])
                blends = _accessor_values(doc, binary, s["output"])
                angles = [
                    [outer.get(round(t[0], 6), static_outer) * (1.0 - b[0])]
                    for t, b in zip(times, blends, strict=True)
                ]
                s["output"] = _add_accessor(doc, binary, angles)
            elif outer_ch is not None:  # the inner cone follows the outer one
                s = samplers[outer_ch["sampler"]]
                values = _accessor_values(doc, binary, s["output"])
                samplers.append(
                    {
                        "input": s["input"],
                        "interpolation": s.get("interpolation", "LINEAR"),
                        "output": _add_accessor(
                            doc, binary, [[v[0] * (1.0 - blend)] for v in values]
                        ),
                    }
                )
                pointer = f"/extensions/KHR_lights_punctual/lights/{light}/spot/innerConeAngle"
                kept.append(
                    {
                        "sampler": len(samplers) - 1,
                        "target": {
                            "path": "pointer",
                            "extensions": {"KHR_animation_pointer": {"pointer": pointer}},
                        },
                    }
                )
        used = sorted({ch["sampler"] for ch in kept})
        renumber = {old: new for new, old in enumerate(used)}
        anim["samplers"] = [samplers[i] for i in used]
        for ch in kept:
            ch["sampler"] = renumber[ch["sampler"]]
        anim["channels"] = kept


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
    fix = None
    if options.get("export_pointer_animation"):
        factors = {}
        for obj in scene.objects:
            if obj.type == "LIGHT" and obj.data.name not in factors:
                factors[obj.data.name] = light_intensity_factor(obj.data, obj)

        def fix(doc, binary):
            fix_pointer_animation(doc, binary, factors)

    return keep_only_camera(glb, scene.camera.name, fix)


def export_frame(scene, frame: int) -> bytes:
    """The scene at `frame` as .glb bytes, through the active camera."""
    return _export(scene, EXPORT_OPTIONS, frame)


def export_animation(scene) -> bytes:
    """The scene with its timeline (frame_start..frame_end) baked into one glTF animation, as
    .glb bytes, through the active camera: frame f of the scene at glTF time
    f / exporter_fps(scene). The current frame is left as it was."""
    return export_animation_reporting(scene)[0]


# Blender 5.0's exporter fails (an IndexError in gather_scene_animations) when it writes the
# material animation of a scene in which a mesh has both a modifier and a material: a rigged or
# subdivided character. Such a scene is exported again without KHR_animation_pointer, and the
# artist is told what that leaves out.
POINTER_FALLBACK_NOTE = (
    "Blender's glTF exporter cannot write this scene's material, light and camera animation "
    "({error}); exported without it: every frame has those settings as at frame 0"
)


def export_animation_reporting(scene) -> tuple[bytes, list[str]]:
    """export_animation, and what the export had to leave out (empty: nothing)."""
    try:
        return _export(scene, ANIMATION_OPTIONS, None), []
    except ExportError as first:
        plain = {**ANIMATION_OPTIONS, "export_pointer_animation": False}
        glb = _export(scene, plain, None)  # its own failure, if any, is the one to report
        lines = [line.strip() for line in str(first).splitlines() if line.strip()]
        return glb, [POINTER_FALLBACK_NOTE.format(error=lines[-1] if lines else "no reason")]
