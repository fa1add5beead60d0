"""Runs inside Blender's Python (the bpy module of .venv-blender), started by
tests/test_cryptomatte_farm.py: opens an EXR of the farm in Blender's compositor and, for each
TYPE=NAME given, extracts that name's matte with the Cryptomatte node (source Image, the
compositor's own decoding of the IDs, coverages and header) and writes the Matte output as an
OpenEXR; prints the paths as one JSON line `RESULT {...}`.

    python tests/blender_cryptomatte.py FARM.exr WIDTH HEIGHT OUTDIR CryptoObject=wheel ...
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import bpy

EXR, WIDTH, HEIGHT, OUTDIR = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), Path(sys.argv[4])
MATTES = [arg.split("=", 1) for arg in sys.argv[5:]]


def main() -> dict:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    image = bpy.data.images.load(EXR)
    # The compositor: a node group whose output is the render's result (Blender 5.0).
    tree = bpy.data.node_groups.new("farm mattes", "CompositorNodeTree")
    tree.interface.new_socket("Image", in_out="OUTPUT", socket_type="NodeSocketColor")
    scene.compositing_node_group = tree
    node = tree.nodes.new("CompositorNodeCryptomatteV2")
    node.source = "IMAGE"
    node.image = image
    out = tree.nodes.new("NodeGroupOutput")
    tree.links.new(node.outputs["Matte"], out.inputs[0])
    # Nothing to render: the compositor's output is the result, at the EXR's size.
    scene.render.engine = "CYCLES"
    scene.cycles.samples = 1
    scene.render.resolution_x, scene.render.resolution_y = WIDTH, HEIGHT
    scene.render.resolution_percentage = 100
    scene.render.use_compositing = True
    settings = scene.render.image_settings
    if hasattr(settings, "media_type"):  # Blender 5.0: the file formats are grouped by media
        settings.media_type = "IMAGE"
    settings.file_format = "OPEN_EXR"
    settings.color_depth = "32"
    settings.color_mode = "RGBA"
    scene.render.use_file_extension = False
    written = {}
    for type_name, name in MATTES:
        node.layer_name = type_name
        node.matte_id = name
        path = OUTDIR / f"{type_name}-{len(written)}.exr"
        scene.render.filepath = str(path)
        bpy.ops.render.render(write_still=True)
        written[f"{type_name}={name}"] = str(path)
    return written


if __name__ == "__main__":
    print("RESULT " + json.dumps(main()), flush=True)
