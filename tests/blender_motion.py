"""Runs inside Blender's Python (the bpy module of .venv-blender), started by
tests/test_motion_blender.py: imports an animated .gltf with Blender's own glTF importer at FPS
frames per second, renders frame FRAME with Cycles (1 sample, box filter, no motion blur) with
the view layer's Vector pass on, writes the render as a multilayer OpenEXR and prints its path
as one JSON line `RESULT {...}`.

    python tests/blender_motion.py SCENE.gltf OUT.exr WIDTH HEIGHT FPS FRAME
"""

from __future__ import annotations

import json
import sys

import bpy

SCENE, OUT = sys.argv[1], sys.argv[2]
WIDTH, HEIGHT, FPS, FRAME = int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5]), int(sys.argv[6])


def main() -> dict:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.fps, scene.render.fps_base = FPS, 1.0  # the importer maps glTF time t to t * fps
    result = bpy.ops.import_scene.gltf(filepath=SCENE)
    assert result == {"FINISHED"}, result
    cameras = [obj for obj in scene.objects if obj.type == "CAMERA"]
    assert len(cameras) == 1, [obj.name for obj in scene.objects]
    scene.camera = cameras[0]
    scene.frame_set(FRAME)
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = 1
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.use_denoising = False
    scene.cycles.pixel_filter_type = "BOX"
    scene.cycles.filter_width = 1.0
    scene.render.use_motion_blur = False  # Cycles writes the Vector pass only without it
    scene.render.resolution_x, scene.render.resolution_y = WIDTH, HEIGHT
    scene.render.resolution_percentage = 100
    scene.render.use_compositing = False
    scene.render.threads_mode = "FIXED"
    scene.render.threads = 1
    bpy.context.view_layer.use_pass_vector = True
    image = scene.render.image_settings
    if hasattr(image, "media_type"):  # Blender 5.0: the file formats are grouped by media
        image.media_type = "MULTI_LAYER_IMAGE"
    image.file_format = "OPEN_EXR_MULTILAYER"
    image.color_depth = "32"
    scene.render.filepath = OUT
    scene.render.use_file_extension = False
    bpy.ops.render.render(write_still=True)
    return {"exr": OUT, "frame": scene.frame_current}


if __name__ == "__main__":
    print("RESULT " + json.dumps(main()), flush=True)
