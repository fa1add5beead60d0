"""Renders a glTF scene with Cycles at settings matched to the farm's path tracer, for
bench/cycles_parity.py. Runs inside Blender's Python (the bpy module of .venv-blender):

    .venv-blender/bin/python bench/support/cycles_render.py CONFIG.json

CONFIG: {"scene": glTF path, "width", "height", "max_depth", "threads",
"renders": [{"spp", "seed", "path"}, ...], "environment": null or {"path", "intensity",
"rotation_deg"}, "microfacet": "multi_ggx" (as imported) or "ggx"}. The scene is imported
once with Blender's own glTF importer (lights in the COMPAT units the exporter of the parity
scenes and the Blender add-on use), then rendered once per entry of "renders" into a 32-bit
float linear EXR (R, G, B: the Combined pass of the render result, no view transform, no
compositor). Prints
`RESULT {"seconds": [...], "camera": NAME}`: the wall time of each bpy.ops.render.render
(scene synchronisation, BVH build, sampling and writing the EXR; not Blender's start-up or the
import).
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
    result = bpy.ops.import_scene.gltf(
        filepath=CONFIG["scene"], export_import_convert_lighting_mode="COMPAT"
    )
    assert result == {"FINISHED"}, result
    scene = bpy.context.scene
    cameras = [o for o in scene.objects if o.type == "CAMERA"]
    if not cameras:
        raise SystemExit(f"{CONFIG['scene']}: no camera (the parity harness needs one)")
    # The farm renders through the first camera of the scene's node tree; the importer makes
    # objects in that order.
    scene.camera = cameras[0]
    return scene


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
    # The importer's Principled BSDFs use multiple-scattering GGX (energy that single
    # scattering loses is put back); glTF's BRDF (Appendix B) is single-scattering GGX.
    # "ggx" makes Cycles compute the spec's model, so what remains is the renderers' own.
    if CONFIG.get("microfacet", "multi_ggx") == "ggx":
        for material in bpy.data.materials:
            for node in material.node_tree.nodes if material.node_tree else ():
                if node.type == "BSDF_PRINCIPLED":
                    node.distribution = "GGX"
    for obj in scene.objects:
        # Shadow-terminator fixes move shadow rays off the surface or bend the shading
        # normal's cosine; the farm does neither.
        obj.cycles.shadow_terminator_offset = 0.0
        obj.cycles.shadow_terminator_geometry_offset = 0.0
    settings = scene.render.image_settings
    settings.file_format = "OPEN_EXR"
    settings.color_depth = "32"
    settings.color_mode = "RGB"
    settings.exr_codec = "ZIP"


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


def main() -> dict:
    scene = import_scene()
    match_settings(scene)
    seconds = []
    for render in CONFIG["renders"]:
        scene.cycles.samples = render["spp"]
        scene.cycles.seed = render["seed"]
        scene.render.filepath = render["path"]
        start = time.perf_counter()
        bpy.ops.render.render(write_still=True)
        seconds.append(time.perf_counter() - start)
    return {"seconds": seconds, "camera": scene.camera.name}


if __name__ == "__main__":
    print("RESULT " + json.dumps(main()), flush=True)
