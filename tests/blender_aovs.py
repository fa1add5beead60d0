"""Runs inside Blender's Python (the bpy module of .venv-blender), started by
tests/test_aovs_blender.py: imports a .gltf with Blender's own glTF importer, renders it with
Cycles (1 sample, no denoising) with the view layer's Depth and Position passes on, writes the
render as a multilayer OpenEXR and prints its path as one JSON line `RESULT {...}`.

    python tests/blender_aovs.py SCENE.gltf OUT.exr
"""

from __future__ import annotations

import json
import sys

import bpy

SCENE, OUT = sys.argv[1], sys.argv[2]


def main() -> dict:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    result = bpy.ops.import_scene.gltf(filepath=SCENE)
    assert result == {"FINISHED"}, result
    scene = bpy.context.scene
    cameras = [obj for obj in scene.objects if obj.type == "CAMERA"]
    assert len(cameras) == 1, [obj.name for obj in scene.objects]
    scene.camera = cameras[0]
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = 1
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.use_denoising = False
    # A box filter one pixel wide: every sample, and so the first one the data passes keep, lies
    # inside its pixel (the default Blackman-Harris of 1.5 pixels reaches into the neighbours).
    scene.cycles.pixel_filter_type = "BOX"
    scene.cycles.filter_width = 1.0
    scene.render.resolution_x, scene.render.resolution_y = 32, 24
    scene.render.resolution_percentage = 100
    scene.render.pixel_aspect_x = scene.render.pixel_aspect_y = 1.0
    scene.render.use_compositing = False
    scene.render.threads_mode = "FIXED"
    scene.render.threads = 1
    layer = bpy.context.view_layer
    layer.use_pass_z = True
    layer.use_pass_position = True
    image = scene.render.image_settings
    if hasattr(image, "media_type"):  # Blender 5.0: the file formats are grouped by media
        image.media_type = "MULTI_LAYER_IMAGE"
    image.file_format = "OPEN_EXR_MULTILAYER"
    image.color_depth = "32"
    image.exr_codec = "ZIP"
    scene.render.filepath = OUT
    scene.render.use_file_extension = False
    bpy.ops.render.render(write_still=True)
    return {"exr": OUT, "camera": cameras[0].name}


if __name__ == "__main__":
    print("RESULT " + json.dumps(main()), flush=True)
