"""Renders a glTF scene with Cycles at settings matched to the farm's path tracer, for
bench/cycles_parity.py. Runs inside Blender's Python (the bpy module of .venv-blender):

    .venv-blender/bin/python bench/support/cycles_render.py CONFIG.json

CONFIG: {"scene": glTF path, "width", "height", "max_depth", "threads",
"renders": [{"spp", "seed", "path", "adaptive": optional {"threshold", "min_samples"}: Cycles'
adaptive sampling on, spp its maximum (bench/adaptive_parity.py), "sample_count_path": optional,
a multilayer EXR for the render's passes with its Debug Sample Count}, ...], "environment": null or
{"path", "intensity",
"rotation_deg"}, "microfacet": "multi_ggx" (as imported) or "ggx", "textures": "as_imported"
or "linear", "volume": "as_imported" or "gltf", "anisotropy": "as_imported" or "gltf",
"frame": null or the frame F of an animated scene to render, "fps": its frame rate,
"importer": "gltf" (default) or "usd", "camera": the camera object's name (default: the first),
"world": "as_imported" to keep a world the USD importer made of a dome light, "lights":
"usd" to undo the USD importer's departures from UsdLux (usd_lights()), "passes": true for the
lobe passes and light groups in a multilayer EXR (enable_passes(), bench/passes_parity.py)}.
The scene is imported once with Blender's own glTF importer (lights in the COMPAT units the
exporter of the parity scenes and the Blender add-on use) or USD importer (bench/usd_parity.py:
bpy.ops.wm.usd_import, subdivision off), then rendered once per entry of
"renders" into a 32-bit float linear EXR (R, G, B: the Combined pass of the render result, no
view transform, no compositor). With a frame, the imported animation is evaluated at frame F
(scene.frame_set(F)): the importer puts a key at glTF time t on frame t x render.fps x
render.fps_base (io_scene_gltf2's animation_node.py), which are set to "fps" before the import,
so F is glTF time F / fps, the farm's time of frame F (domain/frames.py frame_time).
Prints `RESULT {"seconds": [...], "camera": NAME, "keys": ..., "lights": ...}`:
the wall time of each bpy.ops.render.render (scene synchronisation, BVH build, sampling and
writing the EXR; not Blender's start-up or the import), with a frame, where the imported
keys lie (imported_keys()), and for a USD stage what the importer made of its lights
(lights_as_imported()).
"""

from __future__ import annotations

import json
import math
import sys
import time

import bpy

CONFIG = json.loads(open(sys.argv[1]).read())


def import_scene() -> bpy.types.Scene:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    if CONFIG.get("fps"):
        # The importer's frame of glTF time t is t x fps x fps_base (render.fps is whole).
        render = bpy.context.scene.render
        render.fps = max(1, round(CONFIG["fps"]))
        render.fps_base = CONFIG["fps"] / render.fps
    if CONFIG.get("importer", "gltf") == "usd":
        import_usd()
    else:
        result = bpy.ops.import_scene.gltf(
            filepath=CONFIG["scene"], export_import_convert_lighting_mode="COMPAT"
        )
        assert result == {"FINISHED"}, result
    scene = bpy.context.scene
    cameras = [o for o in scene.objects if o.type == "CAMERA"]
    if not cameras:
        raise SystemExit(f"{CONFIG['scene']}: no camera (the parity harness needs one)")
    # The farm renders through the first camera of the scene's node tree; the importer makes
    # objects in that order. A USD stage names the camera the farm chose (its prim's name).
    named = [o for o in cameras if o.name == CONFIG.get("camera")]
    scene.camera = (named or cameras)[0]
    return scene


def import_usd() -> None:
    """The stage through Blender's own USD importer (bpy.ops.wm.usd_import) with its defaults,
    except: subdivision not applied (the farm renders the control cage), and a world to receive
    a dome light (create_world_material writes into the scene's world, which the empty factory
    scene lacks)."""
    scene = bpy.context.scene
    scene.world = bpy.data.worlds.new("World")
    scene.world.use_nodes = True
    scene.world.node_tree.nodes.clear()  # a Background node only if a dome light makes one
    result = bpy.ops.wm.usd_import(filepath=CONFIG["scene"], import_subdivision=False)
    assert result == {"FINISHED"}, result
    # The dome light's world, kept by match_settings (CONFIG "world": "as_imported").
    CONFIG["imported_world"] = scene.world
    if CONFIG.get("lights") == "usd":
        usd_lights(scene)


def usd_lights(scene: bpy.types.Scene) -> None:
    """Undo what Blender 5.0's importer does to lights otherwise than UsdLux says
    (docs/parity.md, "USD stages"), so that what remains is the renderers' own: a
    DistantLight's strength is imported as 4 x intensity ("approximately matches Karma", its
    source says) and its angle doubled; a SphereLight's radius stays in scene units while its
    object takes the stage's metersPerUnit scale, which Cycles does not apply to a point
    light's radius."""
    for obj in scene.objects:
        if obj.type != "LIGHT":
            continue
        light = obj.data
        if light.type == "SUN":
            light.energy /= 4.0
            light.angle /= 2.0
        elif light.type in ("POINT", "SPOT"):
            s = obj.matrix_world.to_scale()
            light.shadow_soft_size *= (abs(s[0]) + abs(s[1]) + abs(s[2])) / 3.0


def match_settings(scene: bpy.types.Scene) -> None:
    """Cycles set to compute what the farm's path tracer computes (docs/parity.md)."""
    scene.render.engine = "CYCLES"
    c = scene.cycles
    c.device = "CPU"
    c.use_adaptive_sampling = False
    c.use_denoising = False
    # The farm averages samples uniformly over each pixel's square: a 1-pixel box filter.
    c.pixel_filter_type = "BOX"
    c.filter_width = 1.0
    # The farm's max_depth D ends a path at its D-th bounce off a surface after the camera
    # ray's hit; Cycles counts bounces after the first hit: D - 1 of every kind.
    bounces = CONFIG["max_depth"] - 1
    c.max_bounces = bounces
    c.diffuse_bounces = bounces
    c.glossy_bounces = bounces
    c.transmission_bounces = bounces
    c.volume_bounces = bounces
    c.transparent_max_bounces = bounces
    # No biasing shortcuts: no clamping, no glossy blur, every light sampled, caustics.
    c.sample_clamp_direct = 0.0
    c.sample_clamp_indirect = 0.0
    c.blur_glossy = 0.0
    c.light_sampling_threshold = 0.0
    c.caustics_reflective = True
    c.caustics_refractive = True
    c.use_guiding = False
    # Pixels sampled independently of their neighbours (no blue-noise dithering between
    # pixels), which the harness's standard errors assume.
    c.sampling_pattern = "TABULATED_SOBOL"
    c.use_animated_seed = False
    # One instant per image, as the farm renders a frame without --shutter (off by default in
    # the factory settings; set so that an animated frame cannot be blurred).
    scene.render.use_motion_blur = False
    scene.render.threads_mode = "FIXED"
    scene.render.threads = CONFIG["threads"]
    scene.render.resolution_x = CONFIG["width"]
    scene.render.resolution_y = CONFIG["height"]
    scene.render.resolution_percentage = 100
    scene.render.film_transparent = False
    scene.render.use_compositing = False
    scene.render.use_sequencer = False
    scene.render.use_persistent_data = False
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = 0.0
    scene.view_settings.gamma = 1.0
    # Black world, as the farm renders where rays escape without an environment map.
    scene.world = None
    if CONFIG.get("environment"):
        scene.world = environment_world(CONFIG["environment"])
    elif CONFIG.get("world") == "as_imported" and imported_world_lights():
        scene.world = CONFIG["imported_world"]
    # The importer's Principled BSDFs use multiple-scattering GGX (energy that single
    # scattering loses is put back); glTF's BRDF (Appendix B) is single-scattering GGX.
    # "ggx" makes Cycles compute the spec's model, so what remains is the renderers' own.
    if CONFIG.get("microfacet", "multi_ggx") == "ggx":
        for node in material_nodes("BSDF_PRINCIPLED"):
            node.distribution = "GGX"
    if CONFIG.get("textures", "as_imported") == "linear":
        decode_textures_first()
    if CONFIG.get("volume", "as_imported") == "gltf":
        beer_lambert_volumes()
    if CONFIG.get("anisotropy", "as_imported") == "gltf":
        gltf_anisotropy()
    for obj in scene.objects:
        # Shadow-terminator fixes move shadow rays off the surface or bend the shading
        # normal's cosine; the farm does neither.
        obj.cycles.shadow_terminator_offset = 0.0
        obj.cycles.shadow_terminator_geometry_offset = 0.0
    for material in bpy.data.materials:
        # Cycles' "Bump Map Correction" (on by default) darkens diffuse light that grazes a
        # normal-mapped surface (Conty Estevez et al.'s bump-terminator shadowing) and bends
        # the normal so that specular reflections stay above the surface; glTF's normalTexture
        # (3.9.3) does neither, nor does the farm.
        material.cycles.use_bump_map_correction = False
    settings = scene.render.image_settings
    settings.file_format = "OPEN_EXR"
    settings.color_depth = "32"
    settings.color_mode = "RGB"
    settings.exr_codec = "ZIP"


def imported_world_lights() -> bool:
    """Whether the USD importer made the world from a dome light (a Background node reached
    from the world output), rather than leaving the empty world made for it."""
    world = CONFIG.get("imported_world")
    if world is None or not world.use_nodes or world.node_tree is None:
        return False
    return any(n.type == "BACKGROUND" for n in world.node_tree.nodes)


def lights_as_imported() -> list[dict]:
    """What the importer made of each light: its type, power (W; a sun's strength, W/m^2),
    colour, size and world scale, so that a difference in light can be traced to the
    importer's conversion (docs/parity.md, "USD stages")."""
    out = []
    for obj in bpy.context.scene.objects:
        if obj.type != "LIGHT":
            continue
        light = obj.data
        entry = {
            "name": obj.name,
            "type": light.type,
            "energy": light.energy,
            "color": list(light.color),
            "scale": list(obj.matrix_world.to_scale()),
        }
        if light.type == "AREA":
            entry.update(shape=light.shape, size=light.size, size_y=light.size_y)
        elif light.type in ("POINT", "SPOT"):
            entry["radius"] = light.shadow_soft_size
        elif light.type == "SUN":
            entry["angle"] = light.angle
        out.append(entry)
    world = CONFIG.get("imported_world")
    if world is not None and imported_world_lights():
        for node in world.node_tree.nodes:
            if node.type == "BACKGROUND":
                colour = node.inputs["Color"]
                out.append({
                    "name": "world",
                    "type": "WORLD",
                    "strength": node.inputs["Strength"].default_value,
                    "color": None if colour.is_linked else list(colour.default_value),
                })  # fmt: skip
    return out


def material_nodes(kind: str):
    """Every shader node of one type in the scene's materials."""
    for material in bpy.data.materials:
        for node in material.node_tree.nodes if material.node_tree else ():
            if node.type == kind:
                yield node


def srgb_to_linear(v):
    """The sRGB transfer function's inverse (IEC 61966-2-1), as the glTF spec defines it."""
    import numpy as np

    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def decode_textures_first() -> None:
    """Replace every 8-bit sRGB image by a linear float copy, so that Cycles filters decoded
    values as glTF asks (and the farm does), instead of filtering the 8-bit sRGB values and
    decoding the result. Alpha and non-colour images are unchanged."""
    import numpy as np

    linear_of = {}
    for image in list(bpy.data.images):
        if image.is_float or image.colorspace_settings.name != "sRGB" or 0 in image.size:
            continue
        w, h = image.size
        pixels = np.empty(w * h * 4, np.float32)
        image.pixels.foreach_get(pixels)  # a byte image's stored values / 255: sRGB-encoded
        pixels = pixels.reshape(-1, 4)
        pixels[:, :3] = srgb_to_linear(pixels[:, :3].astype(np.float64))
        linear = bpy.data.images.new(image.name + ".linear", w, h, alpha=True,
                                     float_buffer=True)  # fmt: skip
        linear.colorspace_settings.name = "Linear Rec.709"
        linear.alpha_mode = image.alpha_mode
        linear.pixels.foreach_set(pixels.ravel())
        linear.pack()
        linear_of[image.name] = linear
    for node in material_nodes("TEX_IMAGE"):
        if node.image is not None and node.image.name in linear_of:
            node.image = linear_of[node.image.name]


def beer_lambert_volumes() -> None:
    """Make every Volume Absorption node absorb as KHR_materials_volume defines it.

    The importer sets the node's colour to attenuationColor c and its density to
    1 / attenuationDistance d; Cycles then absorbs with coefficient density x (1 - colour), so
    light keeps exp(-(1 - c) x / d) over a length x instead of the extension's c^(x / d).
    Here the coefficient per channel becomes -ln(c) / d: density its largest, colour
    1 - coefficient / density."""
    for node in material_nodes("VOLUME_ABSORPTION"):
        colour = node.inputs["Color"].default_value
        density = node.inputs["Density"].default_value
        if not density > 0 or not math.isfinite(density):
            continue
        sigma = [-math.log(max(float(colour[c]), 1e-6)) * density for c in range(3)]
        top = max(sigma)
        if not top > 0:
            continue
        node.inputs["Density"].default_value = top
        node.inputs["Color"].default_value = (*(1.0 - s / top for s in sigma), 1.0)


def gltf_anisotropy() -> None:
    """Make every anisotropic Principled BSDF's GGX the one KHR_materials_anisotropy defines.

    The importer sets Anisotropic to anisotropyStrength s as it is; Cycles then takes alphas
    r^2 / sqrt(1 - 0.9 s) along the tangent and r^2 sqrt(1 - 0.9 s) across it, where the
    extension has mix(r^2, 1, s^2) along the anisotropy direction and r^2 across it. Here
    Roughness and Anisotropic are set so that Cycles' two alphas are the extension's: their
    product gives the roughness, their ratio the anisotropy (Cycles' ratio is at most 10; a
    larger one is clamped there, keeping the product). Linked sockets are left as imported."""
    for node in material_nodes("BSDF_PRINCIPLED"):
        strength_in, rough_in = node.inputs["Anisotropic"], node.inputs["Roughness"]
        if strength_in.is_linked or rough_in.is_linked:
            continue
        s = min(max(float(strength_in.default_value), 0.0), 1.0)
        if s <= 0.0:
            continue
        alpha = float(rough_in.default_value) ** 2
        along, across = alpha + (1.0 - alpha) * s * s, alpha
        # Cycles: along / across = 1 / (1 - 0.9 a), along x across = roughness^4.
        rough_in.default_value = (along * across) ** 0.25
        strength_in.default_value = min((1.0 - across / along) / 0.9, 1.0)


def environment_world(env: dict) -> bpy.types.World:
    """The farm's environment map as Cycles' world: the same texels (closest, as the farm
    looks them up) at the same directions, radiance times the intensity.

    The farm's map (glTF, +Y up) puts column u = 0.5 along -Z (Blender's +Y) and turns the map
    by rotation_deg about +Y (Blender's +Z); Blender's equirectangular lookup puts u = 0.5
    along +X. Both grow u the same way round, so rotating the lookup direction by
    -(90 degrees + rotation_deg) about Z makes Blender read the texel the farm reads."""
    world = bpy.data.worlds.new("Environment")
    tree = world.node_tree
    tree.nodes.clear()
    coords = tree.nodes.new("ShaderNodeTexCoord")
    mapping = tree.nodes.new("ShaderNodeMapping")
    mapping.vector_type = "POINT"
    mapping.inputs["Rotation"].default_value = (0.0, 0.0, -math.radians(90.0 + env["rotation_deg"]))
    tex = tree.nodes.new("ShaderNodeTexEnvironment")
    tex.image = bpy.data.images.load(env["path"])
    tex.interpolation = "Closest"
    tex.projection = "EQUIRECTANGULAR"
    background = tree.nodes.new("ShaderNodeBackground")
    background.inputs["Strength"].default_value = env["intensity"]
    out = tree.nodes.new("ShaderNodeOutputWorld")
    tree.links.new(coords.outputs["Generated"], mapping.inputs["Vector"])
    tree.links.new(mapping.outputs["Vector"], tex.inputs["Vector"])
    tree.links.new(tex.outputs["Color"], background.inputs["Color"])
    tree.links.new(background.outputs["Background"], out.inputs["Surface"])
    return world


def fcurves():
    """Every F-curve of the imported actions (Blender 5.0's layered actions: layers, strips,
    channel bags)."""
    for action in bpy.data.actions:
        for layer in action.layers:
            for strip in layer.strips:
                for bag in strip.channelbags:
                    yield from bag.fcurves


def imported_keys(frame: int) -> dict:
    """Where the importer put the animation's keys: the number of F-curves, the largest
    distance of any key from a whole frame, and, over the F-curves that interpolate (not
    CONSTANT, the exporter's STEP channels of what does not move), the largest distance from
    frame to the curve's nearest key (0: every moving channel has a key on the frame)."""
    curves, off_whole, off_frame = 0, 0.0, 0.0
    for curve in fcurves():
        keys = [k.co[0] for k in curve.keyframe_points]
        if not keys:
            continue
        curves += 1
        off_whole = max(off_whole, max(abs(k - round(k)) for k in keys))
        if any(k.interpolation != "CONSTANT" for k in curve.keyframe_points):
            off_frame = max(off_frame, min(abs(k - frame) for k in keys))
    return {"fcurves": curves, "largest_offset_from_a_whole_frame": off_whole,
            "largest_distance_of_frame_from_a_key": off_frame}  # fmt: skip


# Cycles' passes a farm job's `lobes` rows correspond to (bench/passes_parity.py): each row is
# Cycles' direct or indirect pass times its colour pass (Cycles keeps the colour apart), or a
# pass as it is.
LOBE_PASSES = ("diffuse_direct", "diffuse_indirect", "diffuse_color", "glossy_direct",
               "glossy_indirect", "glossy_color", "transmission_direct",
               "transmission_indirect", "transmission_color", "emit", "environment")  # fmt: skip


def light_group_name(name: str) -> str:
    """The farm's light group of a node name (server/renderfarm/domain/light_groups.py)."""
    import re

    return re.sub(r"[^A-Za-z0-9_-]", "_", name.strip()) or "unnamed"


def enable_passes(scene: bpy.types.Scene) -> dict:
    """CONFIG "passes": the lobe passes and one light group per light and emissive object
    (named as the farm names the glTF node's group) and the world's, into a multilayer EXR.
    Returns {light group: [objects]}."""
    layer = scene.view_layers[0]
    for name in LOBE_PASSES:
        setattr(layer, f"use_pass_{name}", True)
    groups: dict[str, list[str]] = {}
    for obj in scene.objects:
        emits = obj.type == "LIGHT" or any(
            slot.material and any(
                n.type == "EMISSION" or (n.type == "BSDF_PRINCIPLED"
                                         and n.inputs["Emission Strength"].default_value > 0
                                         and any(n.inputs["Emission Color"].default_value[:3]))
                for n in (slot.material.node_tree.nodes if slot.material.node_tree else ())
            )
            for slot in obj.material_slots
        )  # fmt: skip
        if emits:
            name = light_group_name(obj.name)
            if name not in layer.lightgroups:
                layer.lightgroups.add(name=name)
            obj.lightgroup = name
            groups.setdefault(name, []).append(obj.name)
    if scene.world is not None:
        layer.lightgroups.add(name="environment")
        scene.world.lightgroup = "environment"
        groups["environment"] = []
    settings = scene.render.image_settings
    settings.media_type = "MULTI_LAYER_IMAGE"  # Blender 5.0: then OpenEXR MultiLayer only
    settings.file_format = "OPEN_EXR_MULTILAYER"
    settings.color_depth = "32"
    return groups


def save_sample_count(scene: bpy.types.Scene, path: str) -> None:
    """The last render's passes, its Debug Sample Count among them (each pixel's samples over
    the render's sample count), into a multilayer EXR at path; the image settings are
    restored for the renders after it."""
    settings = scene.render.image_settings
    # Switching the media type resets the depth and codec (to half floats): every one is kept.
    kept = ("media_type", "file_format", "color_depth", "color_mode", "exr_codec")
    before = {name: getattr(settings, name) for name in kept}
    settings.media_type = "MULTI_LAYER_IMAGE"
    settings.file_format = "OPEN_EXR_MULTILAYER"
    settings.color_depth = "32"
    bpy.data.images["Render Result"].save_render(filepath=path, scene=scene)
    for name in kept:
        setattr(settings, name, before[name])
    changed = [name for name in kept if getattr(settings, name) != before[name]]
    if changed:
        raise RuntimeError(f"image settings not restored after the sample count: {changed}")


def main() -> dict:
    scene = import_scene()
    match_settings(scene)
    groups = enable_passes(scene) if CONFIG.get("passes") else None
    keys = None
    if CONFIG.get("frame") is not None:
        scene.frame_set(CONFIG["frame"])
        keys = imported_keys(CONFIG["frame"])
    seconds = []
    for render in CONFIG["renders"]:
        scene.cycles.samples = render["spp"]
        scene.cycles.seed = render["seed"]
        adaptive = render.get("adaptive")
        scene.cycles.use_adaptive_sampling = adaptive is not None
        if adaptive is not None:
            scene.cycles.adaptive_threshold = adaptive["threshold"]
            scene.cycles.adaptive_min_samples = adaptive["min_samples"]
        scene.render.filepath = render["path"]
        counted = render.get("sample_count_path")
        scene.view_layers[0].cycles.pass_debug_sample_count = bool(counted)
        start = time.perf_counter()
        bpy.ops.render.render(write_still=True)
        seconds.append(time.perf_counter() - start)
        if counted:
            save_sample_count(scene, counted)
    lights = lights_as_imported() if CONFIG.get("importer") == "usd" else None
    return {"seconds": seconds, "camera": scene.camera.name, "keys": keys, "lights": lights,
            "light_groups": groups}  # fmt: skip


if __name__ == "__main__":
    print("RESULT " + json.dumps(main()), flush=True)
