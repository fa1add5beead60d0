"""The Cycles parity suite's scenes, each isolating one feature, built in Blender with bpy and
exported with Blender's own glTF exporter (the options the Blender add-on uses), so that the
glTF the farm reads is what a Blender user would produce. Textures are made here with numpy.

Runs inside Blender's Python (the bpy module of .venv-blender), started by
bench/cycles_parity.py:

    .venv-blender/bin/python bench/support/parity_scenes.py OUT_DIR NAME [NAME ...]

writes OUT_DIR/NAME.glb for each scene (and OUT_DIR/NAME-environment.hdr for a scene lit by an
environment map, which glTF cannot hold) and prints
`RESULT {"NAME": {"scene": "OUT_DIR/NAME.glb", "environment": null or its path}, ...}`.
Imported without bpy (by bench/cycles_parity.py), it only lists the scenes: SCENES maps each
name to a one-line description.

`animated_shot` is animated (48 frames at 24 fps): it is exported with the Blender add-on's
animation options (integrations/blender/renderfarm_blender/export.py ANIMATION_OPTIONS: the
scene's timeline baked into one glTF animation, frame f at glTF time f / fps; see
export_animated() for the one option left off), and the harness renders chosen frames of it
(bench/cycles_parity.py --frame).

Every scene but `environment` is lit by an emissive quad (the farm renders Blender's area
lights not at all, see docs/blender.md, "Not rendered by the farm") and some by a point light
of radius 0; the world is black.
"""

from __future__ import annotations

import json
import math
import os
import struct
import sys

import numpy as np

try:
    import bpy
    from mathutils import Vector
except ImportError:  # imported by bench/cycles_parity.py for the names only
    bpy = None

# The glTF exporter's options of the Blender add-on (integrations/blender, export.py): lights in
# COMPAT units (W/sr, which keeps their ratio to emissive materials).
EXPORT_OPTIONS = {
    "export_format": "GLB",
    "use_renderable": True,
    "export_apply": True,
    "export_cameras": True,
    "export_lights": True,
    "export_import_convert_lighting_mode": "COMPAT",
    "export_animations": False,
    "export_yup": True,
    "export_extras": False,
    "check_existing": False,
}

SCENES = {
    "rough_dielectric": "three orange dielectric spheres, roughness 0.1, 0.4 and 0.8",
    "metal": "a rough gold floor seen at grazing angles, reflecting two boxes",
    "glass": "a smooth glass sphere (IOR 1.5) on a checker floor",
    "glass_volume": "the glass sphere with KHR_materials_volume absorption (blue-green)",
    "rough_glass": "a frosted glass sphere (IOR 1.5, roughness 0.3) on a checker floor",
    "alpha_mask": "an alpha-masked leaf card (MASK, cutoff 0.5) casting a shadow",
    "vertex_colors": "an icosphere coloured by a COLOR_0 vertex attribute",
    "emissive_texture": "a panel with an emissive texture lighting a floor and a box",
    "blended_decal": "a soft-edged decal (alphaMode BLEND) lying on a floor",
    "clearcoat": "a red sphere with a clear coat (KHR_materials_clearcoat)",
    "sheen": "a dark blue sphere with sheen (KHR_materials_sheen)",
    "normal_floor": "a floor with a normal map and a roughness texture of thin lines",
    "two_sided_emitter": "a floor lit only by the back face of a double-sided emissive quad",
    "environment": "a diffuse and a glossy sphere lit only by an environment map with a sun",
    "combined": "all of the above in one scene, under the environment map and two lights",
    "anisotropy": "two brushed-metal spheres (anisotropy 0.6, rotation 0 and 90 degrees) and a "
    "black anisotropic dielectric (KHR_materials_anisotropy)",
    "specular_color": "a black and a white dielectric sphere with an orange specular colour "
    "(KHR_materials_specular)",
    "animated_shot": "48 frames at 24 fps, Bezier-eased: a camera dollying in under a Track To "
    "constraint, a box turning under a turning parent, a cylinder skinned to two bones",
}

# The realistic suite (#38; bench/cycles_parity.py --realistic): scenes like those studios
# render, where most of the noise is indirect light, glossy reflections and caustics rather
# than one feature. Not part of --suite.
REALISTIC = {
    "realistic_floor": "a textured, normal-mapped checker floor of rough dielectric tiles with "
    "thin metallic grout, a gold, a red glossy and a glass sphere (KHR_materials_volume), "
    "instanced prisms, a torus and one emissive panel",
    "interior_window": "a white room lit through one window by a sun lamp and a sky map "
    "(indirect-dominated), a wooden floor, a sofa block and a glossy table",
    "product_hdr": "a product shot on a rough plastic backdrop under a sky map with a small "
    "bright sun: a glass bottle, a brushed-metal can and rough plastic blocks",
}
SCENES.update(REALISTIC)

# The animated scenes: their frame rate, the first and last frame of their timeline, and the
# frames bench/cycles_parity.py compares when not given --frame.
ANIMATED = {"animated_shot": {"fps": 24.0, "frames": (1, 48), "compare": (1, 24, 48)}}

# The extension each feature's scene exists for: build() checks that the exporter wrote it.
REQUIRED_EXTENSIONS = {
    "anisotropy": "KHR_materials_anisotropy",
    "specular_color": "KHR_materials_specular",
}


# --- building blocks ------------------------------------------------------------------------


def empty_scene():
    bpy.ops.wm.read_factory_settings(use_empty=True)
    return bpy.context.scene


def principled(name: str, color=(0.8, 0.8, 0.8), roughness=0.5, metallic=0.0, **inputs):
    """A Principled BSDF material; inputs are further socket values by name."""
    mat = bpy.data.materials.new(name)
    nodes = mat.node_tree.nodes
    bsdf = nodes.get("Principled BSDF")
    if bsdf is None:
        nodes.clear()
        bsdf = nodes.new("ShaderNodeBsdfPrincipled")
        out = nodes.new("ShaderNodeOutputMaterial")
        mat.node_tree.links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
    bsdf.inputs["Base Color"].default_value = (*color, 1.0)
    bsdf.inputs["Roughness"].default_value = roughness
    bsdf.inputs["Metallic"].default_value = metallic
    for socket, value in inputs.items():
        bsdf.inputs[socket].default_value = value
    return mat


def bsdf_of(mat):
    return mat.node_tree.nodes["Principled BSDF"]


def image(name: str, rgba: np.ndarray, non_color: bool = False):
    """A packed 8-bit image from an HxWx4 float array in [0, 1], row 0 at the top."""
    h, w, _ = rgba.shape
    img = bpy.data.images.new(name, width=w, height=h, alpha=True)
    if non_color:
        img.colorspace_settings.name = "Non-Color"
    # Blender's pixel rows start at the bottom.
    img.pixels.foreach_set(np.ascontiguousarray(rgba[::-1], dtype=np.float32).ravel())
    img.pack()
    return img


def texture(mat, img, socket: str | None, alpha_socket: str | None = None):
    """An Image Texture node of img feeding the BSDF's socket (and its alpha another)."""
    node = mat.node_tree.nodes.new("ShaderNodeTexImage")
    node.image = img
    if socket:
        mat.node_tree.links.new(node.outputs["Color"], bsdf_of(mat).inputs[socket])
    if alpha_socket:
        mat.node_tree.links.new(node.outputs["Alpha"], bsdf_of(mat).inputs[alpha_socket])
    return node


def normal_map(mat, rgba: np.ndarray, name: str) -> None:
    """A tangent-space normal map (RGB in [0, 1]) on the material's BSDF, through a Normal Map
    node, as Blender's exporter reads it into normalTexture."""
    tree = mat.node_tree
    tex = texture(mat, image(name, rgba, non_color=True), None)
    nmap = tree.nodes.new("ShaderNodeNormalMap")
    tree.links.new(tex.outputs["Color"], nmap.inputs["Color"])
    tree.links.new(nmap.outputs["Normal"], bsdf_of(mat).inputs["Normal"])


def channel_map(mat, rgba: np.ndarray, name: str, channel: str, socket: str) -> None:
    """One channel (Red, Green, Blue) of a linear texture feeding a BSDF socket (Roughness,
    Metallic), which the exporter packs into metallicRoughnessTexture."""
    tree = mat.node_tree
    tex = texture(mat, image(name, rgba, non_color=True), None)
    sep = tree.nodes.new("ShaderNodeSeparateColor")
    tree.links.new(tex.outputs["Color"], sep.inputs["Color"])
    tree.links.new(sep.outputs[channel], bsdf_of(mat).inputs[socket])


def add(kind: str, name: str, material, location=(0, 0, 0), smooth=False, **kwargs):
    ops = {
        "plane": bpy.ops.mesh.primitive_plane_add,
        "cube": bpy.ops.mesh.primitive_cube_add,
        "sphere": bpy.ops.mesh.primitive_uv_sphere_add,
        "ico": bpy.ops.mesh.primitive_ico_sphere_add,
    }
    ops[kind](location=location, **kwargs)
    obj = bpy.context.active_object
    obj.name = name
    obj.data.materials.append(material)
    if smooth:
        bpy.ops.object.shade_smooth()
    return obj


def sphere(name: str, material, location, radius=0.6):
    return add("sphere", name, material, location, smooth=True, segments=64, ring_count=32,
               radius=radius)  # fmt: skip


def floor(material=None, size=8.0):
    return add("plane", "Floor", material or principled("Floor", (0.5, 0.5, 0.5), 0.8), size=size)


def quad_light(location=(0, 0, 3.0), size=2.0, strength=6.0, rotation=(math.pi, 0, 0)):
    """An emissive quad, its front (the plane's normal, +Z before rotation) facing down by
    default; black so that it only emits."""
    mat = principled("Light", (0.0, 0.0, 0.0), 1.0)
    bsdf = bsdf_of(mat)
    bsdf.inputs["Emission Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    bsdf.inputs["Emission Strength"].default_value = strength
    obj = add("plane", "LightQuad", mat, location, size=size)
    obj.rotation_euler = rotation
    return obj


def point_light(location, watts: float):
    light = bpy.data.objects.new("Lamp", bpy.data.lights.new("Lamp", "POINT"))
    light.data.energy = watts
    light.data.shadow_soft_size = 0.0  # the farm ignores the radius
    light.location = location
    bpy.context.scene.collection.objects.link(light)
    return light


def camera(location=(0.0, -6.0, 3.0), target=(0.0, 0.0, 0.6), lens=50.0):
    scene = bpy.context.scene
    cam = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    cam.data.lens = lens
    scene.collection.objects.link(cam)
    cam.location = location
    cam.rotation_euler = (Vector(target) - cam.location).to_track_quat("-Z", "Y").to_euler()
    scene.camera = cam
    return cam


def checker(n=256, squares=8, a=(0.85, 0.85, 0.85), b=(0.1, 0.1, 0.1)) -> np.ndarray:
    y, x = np.mgrid[0:n, 0:n] * squares // n
    mask = ((x + y) % 2 == 0)[..., None]
    rgb = np.where(mask, np.array(a), np.array(b))
    return np.concatenate([rgb, np.ones((n, n, 1))], axis=-1)


# --- the features' materials and objects --------------------------------------------------


def glass_material(volume: bool, roughness: float = 0.0):
    glass = principled(
        "Glass", (1.0, 1.0, 1.0), roughness, **{"Transmission Weight": 1.0, "IOR": 1.5}
    )
    if volume:
        from io_scene_gltf2.blender.com.material_helpers import (
            create_settings_group,
            get_gltf_node_name,
        )

        # KHR_materials_volume as the exporter reads it: a Volume Absorption node on the
        # output's Volume socket (attenuation colour, distance = 1 / density) and the
        # thickness on a "glTF Material Output" group node (0 would mean thin-walled).
        tree = glass.node_tree
        absorb = tree.nodes.new("ShaderNodeVolumeAbsorption")
        absorb.inputs["Color"].default_value = (0.2, 0.6, 0.9, 1.0)
        absorb.inputs["Density"].default_value = 1.5
        tree.links.new(absorb.outputs[0], tree.get_output_node("ALL").inputs["Volume"])
        group = bpy.data.node_groups.get(get_gltf_node_name()) or create_settings_group(
            get_gltf_node_name()
        )
        node = tree.nodes.new("ShaderNodeGroup")
        node.node_tree = group
        node.inputs["Thickness"].default_value = 1.2
    return glass


def checker_material():
    mat = principled("Checker", roughness=0.7)
    texture(mat, image("Checker", checker()), "Base Color")
    return mat


def leaf(n=256) -> np.ndarray:
    """A green leaf (an ellipse with a stem and a midrib) on transparent black."""
    y, x = (np.mgrid[0:n, 0:n] + 0.5) / n * 2.0 - 1.0
    blade = (x / 0.55) ** 2 + ((y + 0.1) / 0.85) ** 2 < 1.0
    stem = (np.abs(x) < 0.03) & (y > 0.6)
    alpha = (blade | stem).astype(float)
    midrib = np.abs(x) < 0.02
    rgb = np.where(midrib[..., None], [0.5, 0.7, 0.2], [0.1, 0.45, 0.08])
    return np.concatenate([rgb, alpha[..., None]], axis=-1)


def leaf_card(location, size=1.8, turn=0.3):
    mat = principled("Leaf", roughness=0.6)
    tree = mat.node_tree
    tex = texture(mat, image("Leaf", leaf()), "Base Color")
    # Alpha -> Math Round -> Alpha: what the exporter writes as alphaMode MASK, cutoff 0.5.
    rnd = tree.nodes.new("ShaderNodeMath")
    rnd.operation = "ROUND"
    tree.links.new(tex.outputs["Alpha"], rnd.inputs[0])
    tree.links.new(rnd.outputs[0], bsdf_of(mat).inputs["Alpha"])
    card = add("plane", "LeafCard", mat, location, size=size)
    card.rotation_euler = (math.pi / 2, 0, turn)  # standing up, facing the camera
    return card


def painted_icosphere(location, radius=0.9):
    mat = principled("Painted", roughness=0.5)
    attr_node = mat.node_tree.nodes.new("ShaderNodeVertexColor")
    attr_node.layer_name = "Col"
    mat.node_tree.links.new(attr_node.outputs["Color"], bsdf_of(mat).inputs["Base Color"])
    obj = add("ico", "Painted", mat, location, subdivisions=3, radius=radius)
    mesh = obj.data
    color = mesh.color_attributes.new("Col", "FLOAT_COLOR", "POINT")
    co = np.empty(len(mesh.vertices) * 3)
    mesh.vertices.foreach_get("co", co)
    co = co.reshape(-1, 3) / radius
    rgba = np.concatenate([0.5 + 0.45 * co, np.ones((len(co), 1))], axis=-1)
    color.data.foreach_set("color", rgba.astype(np.float32).ravel())
    mesh.color_attributes.active_color = color
    return obj


def screen(location, size=2.0):
    """A standing panel with an emissive texture of stripes, its front towards -Y."""
    n = 128
    y, x = (np.mgrid[0:n, 0:n] + 0.5) / n
    stripes = np.stack([(x * 4 % 1 < 0.5), (y * 3 % 1 < 0.5), ((x + y) * 2 % 1 < 0.3)], -1)
    rgba = np.concatenate([0.05 + 0.95 * stripes, np.ones((n, n, 1))], axis=-1)
    mat = principled("Screen", (0.0, 0.0, 0.0), 0.8)
    texture(mat, image("Screen", rgba), "Emission Color")
    bsdf_of(mat).inputs["Emission Strength"].default_value = 4.0
    panel = add("plane", "Screen", mat, location, size=size)
    panel.rotation_euler = (math.pi / 2, 0, 0)
    return panel


def decal(location, size=2.5):
    n = 128
    y, x = (np.mgrid[0:n, 0:n] + 0.5) / n * 2.0 - 1.0
    alpha = np.clip((0.9 - np.hypot(x, y)) / 0.4, 0.0, 1.0)
    rgb = np.where((np.abs(x) < 0.15)[..., None], [0.9, 0.8, 0.1], [0.8, 0.05, 0.05])
    mat = principled("Decal", roughness=0.5)
    texture(mat, image("Decal", np.concatenate([rgb, alpha[..., None]], -1)), "Base Color",
            "Alpha")  # fmt: skip
    return add("plane", "Decal", mat, location, size=size)


def coat_material():
    return principled("Coated", (0.7, 0.05, 0.05), 0.5,
                      **{"Coat Weight": 1.0, "Coat Roughness": 0.03})  # fmt: skip


def sheen_material():
    return principled("Velvet", (0.05, 0.08, 0.3), 0.6,
                      **{"Sheen Weight": 1.0, "Sheen Roughness": 0.4})  # fmt: skip


def grooved_material():
    """A normal map of grooves along v and a roughness texture: 0.6 with thin smooth lines."""
    n = 256
    y, x = (np.mgrid[0:n, 0:n] + 0.5) / n
    # A tangent-space normal tilting in x (16 periods of a cosine), encoded in [0, 1].
    nx = 0.5 * np.cos(2.0 * np.pi * 16.0 * x)
    nrm = np.stack([nx, np.zeros_like(nx), np.ones_like(nx)], -1)
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    normal = np.concatenate([nrm * 0.5 + 0.5, np.ones((n, n, 1))], -1)
    # Lines (roughness 0.05) two pixels wide across the grooves, every 32 pixels.
    rough = np.where((y * n % 32) < 2, 0.05, 0.6)
    rough_img = np.concatenate([np.repeat(rough[..., None], 3, -1), np.ones((n, n, 1))], -1)
    mat = principled("Grooved", (0.6, 0.6, 0.65), 0.6)
    normal_map(mat, normal, "GroovesNormal")
    # Roughness from the green channel, as glTF's metallicRoughnessTexture holds it.
    channel_map(mat, rough_img, "Lines", "Green", "Roughness")
    return mat


# --- the scenes -----------------------------------------------------------------------------


def rough_dielectric():
    floor()
    for i, roughness in enumerate((0.1, 0.4, 0.8)):
        mat = principled(f"Rough{roughness}", (0.8, 0.3, 0.08), roughness)
        sphere(f"Sphere{i}", mat, (-1.4 + 1.4 * i, 0.0, 0.6))
    quad_light()
    point_light((3.0, -2.0, 4.0), 400.0)
    camera()


def metal():
    gold = principled("Gold", (0.95, 0.7, 0.35), 0.25, metallic=1.0)
    floor(gold, size=12.0)
    add("cube", "RedBox", principled("Red", (0.8, 0.1, 0.08), 0.6), (-0.8, 1.0, 0.5), size=1.0)
    add("cube", "BlueBox", principled("Blue", (0.1, 0.2, 0.8), 0.6), (1.0, 2.2, 0.5), size=1.0)
    quad_light((0.0, 1.5, 3.0), size=3.0, strength=5.0)
    # A light low behind the boxes, its front (-Y) facing the camera: its grazing reflection.
    quad_light((0.0, 6.0, 1.0), size=2.0, strength=8.0, rotation=(math.pi / 2, 0, 0))
    camera((0.0, -6.0, 0.45), (0.0, 1.5, 0.4), lens=40.0)


def _glass(volume: bool, roughness: float = 0.0):
    floor(checker_material())
    sphere("GlassBall", glass_material(volume, roughness), (0.0, 0.0, 0.7), radius=0.7)
    quad_light((0.5, 0.5, 3.0))
    point_light((-2.5, 1.5, 3.5), 300.0)
    camera()


def glass():
    _glass(False)


def glass_volume():
    _glass(True)


def rough_glass():
    """KHR_materials_transmission with roughness: the exporter writes the Principled BSDF's
    roughness as the material's roughnessFactor, which shapes both the reflection and the
    microfacet BTDF; Blender's importer maps it back onto the Principled BSDF, whose
    transmission is Cycles' rough dielectric (GGX, multiple-scattering by default)."""
    _glass(False, 0.3)


def alpha_mask():
    floor()
    leaf_card((0.0, 0.0, 1.1))
    quad_light((0.0, 2.0, 3.5), size=1.5, strength=4.0)
    point_light((0.5, -3.0, 2.5), 500.0)  # in front: the card's shadow falls behind it
    camera((1.5, -6.0, 2.0), (0.0, 0.5, 0.8))


def vertex_colors():
    floor()
    painted_icosphere((0.0, 0.0, 0.9))
    quad_light()
    point_light((-3.0, -2.0, 3.0), 300.0)
    camera()


def emissive_texture():
    floor()
    add("cube", "Box", principled("White", (0.8, 0.8, 0.8), 0.6), (1.2, -0.3, 0.4), size=0.8)
    screen((-0.3, 1.0, 1.0))
    quad_light((0.0, 0.0, 4.0), size=1.0, strength=1.5)
    camera()


def blended_decal():
    floor()
    decal((0.0, 0.0, 0.01))
    add("cube", "Box", principled("Grey", (0.6, 0.6, 0.6), 0.5), (1.8, 1.0, 0.5), size=1.0)
    quad_light()
    point_light((2.0, -3.0, 3.0), 300.0)
    camera()


def clearcoat():
    floor()
    sphere("Coated", coat_material(), (0.0, 0.0, 0.8), radius=0.8)
    quad_light()
    point_light((3.0, -2.0, 4.0), 400.0)
    camera()


def sheen():
    floor()
    sphere("Velvet", sheen_material(), (0.0, 0.0, 0.8), radius=0.8)
    quad_light()
    point_light((-3.0, 3.0, 2.0), 600.0)  # behind: sheen shows at grazing angles
    camera()


def normal_floor():
    floor(grooved_material(), size=6.0)
    # A low light across the floor, its front towards -Y and a little down: the grooves and
    # lines show in its glancing reflection.
    quad_light((0.0, 4.0, 0.8), size=2.0, strength=8.0, rotation=(math.pi / 2 + 0.3, 0, 0))
    camera((0.0, -4.5, 2.0), (0.0, 0.5, 0.0))


def two_sided_emitter():
    # glTF: a doubleSided material's back face is lit (and so emits) as its front, with the
    # normal reversed; Blender's exporter writes doubleSided for a material without backface
    # culling, and Cycles emits from both faces.
    floor()
    add("cube", "Box", principled("White", (0.8, 0.8, 0.8), 0.6), (0.0, 0.0, 0.5), size=1.0)
    quad_light((0.0, 0.0, 2.5), size=2.0, strength=6.0, rotation=(0, 0, 0))  # front faces up
    camera()


def sky_map(width=512, height=256, with_sun: bool = True) -> np.ndarray:
    """An equirectangular sky in the farm's convention (docs/settings.md, `environment`: column
    u = 0.5 looks along glTF -Z, u grows towards +X, row 0 is straight up): a blue gradient, a dark
    ground and a small bright sun off to one side, so that a turned or mirrored map shows."""
    v, u = (np.mgrid[0:height, 0:width] + 0.5) / np.array([height, width])[:, None, None]
    theta, phi = v * np.pi, (u - 0.5) * 2.0 * np.pi
    d = np.stack([np.sin(theta) * np.sin(phi), np.cos(theta), -np.sin(theta) * np.cos(phi)], -1)
    up = np.clip(d[..., 1], 0.0, 1.0)[..., None]
    sky = np.where(d[..., 1:2] > 0.0, (1.0 - up) * [0.9, 0.9, 1.0] + up * [0.2, 0.35, 0.8],
                   [0.12, 0.1, 0.08])  # fmt: skip
    sun = np.array([0.6, 0.55, -0.58])  # glTF axes: high, ahead of the camera, to its right
    sun /= np.linalg.norm(sun)
    disc = (d @ sun) > math.cos(math.radians(4.0))
    return np.where(disc[..., None], [400.0, 360.0, 300.0], sky) if with_sun else sky


def environment():
    floor(size=30.0)
    sphere("Matte", principled("Matte", (0.7, 0.7, 0.7), 0.9), (-0.8, 0.0, 0.6))
    sphere("Glossy", principled("Glossy", (0.9, 0.9, 0.9), 0.15, metallic=1.0), (0.8, 0.0, 0.6))
    camera((0.0, -6.0, 1.6), (0.0, 0.0, 0.8))
    return sky_map()


def combined():
    """Every feature at once: the grooved floor, three rough spheres, gold, glass with and
    without volume, the leaf card, the painted icosphere, the screen, the decal, coat, sheen,
    under the sky map, a quad light and a point light."""
    floor(grooved_material(), size=14.0)
    for i, roughness in enumerate((0.1, 0.4, 0.8)):
        mat = principled(f"Rough{roughness}", (0.8, 0.3, 0.08), roughness)
        sphere(f"Rough{i}", mat, (-3.0 + 0.9 * i, -1.0, 0.4), radius=0.4)
    gold = principled("Gold", (0.95, 0.7, 0.35), 0.25, metallic=1.0)
    add("cube", "GoldBox", gold, (-0.1, -1.0, 0.4), size=0.8)
    sphere("Glass", glass_material(False), (0.9, -1.0, 0.4), radius=0.4)
    sphere("GlassVolume", glass_material(True), (1.9, -1.0, 0.4), radius=0.4)
    sphere("Coated", coat_material(), (2.9, -1.0, 0.4), radius=0.4)
    sphere("Velvet", sheen_material(), (-2.4, 0.6, 0.5), radius=0.5)
    painted_icosphere((-0.9, 0.6, 0.6), radius=0.6)
    leaf_card((0.6, 0.8, 0.8), size=1.4, turn=0.2)
    decal((2.0, 0.5, 0.01), size=1.6)
    screen((0.0, 2.5, 1.0), size=2.0)
    quad_light((0.0, -0.5, 4.0), size=2.0, strength=4.0)
    point_light((3.0, -3.0, 3.5), 400.0)
    camera((0.0, -7.5, 3.2), (0.0, 0.0, 0.5), lens=35.0)
    return sky_map()


def tiles_textures(n=512, tiles=8, grout=3):
    """The realistic floor's textures (row 0 at the top): base colour (warm and cool tiles,
    each a little different, dark grout), roughness and metallic (0.35 dielectric tiles, 0.25
    metallic grout lines `grout` pixels wide) and a tangent-space normal map bevelling each
    tile's edges."""
    y, x = np.mgrid[0:n, 0:n]
    size = n // tiles
    tx, ty = x // size, y // size
    fx, fy = x % size, y % size
    line = (fx < grout) | (fy < grout)
    rng = np.random.default_rng(3)
    shade = rng.uniform(0.85, 1.1, (tiles, tiles))[ty, tx][..., None]
    warm = ((tx + ty) % 2 == 0)[..., None]
    colour = np.where(warm, [0.75, 0.55, 0.4], [0.45, 0.5, 0.55]) * shade
    colour = np.where(line[..., None], [0.2, 0.2, 0.2], np.clip(colour, 0.0, 1.0))
    alpha = np.ones((n, n, 1))
    rough = np.where(line, 0.25, 0.35)
    metal = np.where(line, 1.0, 0.0)
    # Bevel: the normal tilts towards the tile's centre within 6 pixels of its edges.
    bevel = 6.0
    dx = np.where(fx - grout < bevel, -(1 - (fx - grout) / bevel), 0.0) + np.where(
        size - fx < bevel, 1 - (size - fx) / bevel, 0.0
    )
    dy = np.where(fy - grout < bevel, -(1 - (fy - grout) / bevel), 0.0) + np.where(
        size - fy < bevel, 1 - (size - fy) / bevel, 0.0
    )
    nrm = np.stack([-0.5 * dx, 0.5 * dy, np.ones_like(dx, dtype=float)], -1)
    nrm = np.where(line[..., None], [0.0, 0.0, 1.0], nrm)
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    grey = lambda v: np.concatenate([np.repeat(v[..., None], 3, -1), alpha], -1)  # noqa: E731
    return (np.concatenate([colour, alpha], -1), grey(rough), grey(metal),
            np.concatenate([nrm * 0.5 + 0.5, alpha], -1))  # fmt: skip


def tiled_floor_material():
    colour, rough, metal, normal = tiles_textures()
    mat = principled("Tiles", (1.0, 1.0, 1.0), 0.35)
    texture(mat, image("TilesColour", colour), "Base Color")
    channel_map(mat, rough, "TilesRoughness", "Red", "Roughness")
    channel_map(mat, metal, "TilesMetallic", "Red", "Metallic")
    normal_map(mat, normal, "TilesNormal")
    return mat


def realistic_floor():
    """The scene of #38's measurement: 12 bounces at 320x240 in the issue (--realistic)."""
    floor(tiled_floor_material(), size=10.0)
    sphere("Gold", principled("Gold", (1.0, 0.77, 0.34), 0.2, metallic=1.0), (-1.4, 0.3, 0.6))
    sphere("RedGloss", principled("RedGloss", (0.7, 0.05, 0.04), 0.08), (0.0, 0.9, 0.6))
    sphere("GlassBall", glass_material(True), (1.3, -0.2, 0.6))
    prism_mat = principled("Prism", (0.2, 0.45, 0.8), 0.4)
    bpy.ops.mesh.primitive_cylinder_add(vertices=3, radius=0.3, depth=0.6,
                                        location=(-2.2, -1.2, 0.3))  # fmt: skip
    prism = bpy.context.active_object
    prism.name = "Prism"
    prism.data.materials.append(prism_mat)
    for i, (x, y, turn) in enumerate(((-1.4, -1.6, 0.7), (-0.5, -1.9, 1.9), (0.4, -1.7, 2.6))):
        twin = prism.copy()  # a linked duplicate: one mesh, exported once, used by each node
        twin.name = f"Prism{i}"
        twin.location = (x, y, 0.3)
        twin.rotation_euler = (0.0, 0.0, turn)
        bpy.context.scene.collection.objects.link(twin)
    bpy.ops.mesh.primitive_torus_add(major_radius=0.45, minor_radius=0.15,
                                     location=(2.4, 1.2, 0.15))  # fmt: skip
    torus = bpy.context.active_object
    torus.name = "Torus"
    torus.data.materials.append(principled("TorusPaint", (0.85, 0.85, 0.8), 0.5))
    bpy.ops.object.shade_smooth()
    quad_light((1.5, 2.5, 3.2), size=1.6, strength=12.0, rotation=(math.radians(150), 0, 0))
    camera((0.0, -6.5, 2.6), (0.0, 0.0, 0.4), lens=35.0)


def interior_window():
    """A 6 x 5 x 3 m room whose -Y wall has a 1.6 x 1.4 m window; a sun lamp shines through it
    onto the floor and the sky map lights the room through it: nearly everything the camera
    sees is indirect light."""
    white = principled("Plaster", (0.8, 0.78, 0.75), 0.9)
    wood = principled("Wood", (1.0, 1.0, 1.0), 0.45)
    y, x = np.mgrid[0:256, 0:256]
    plank = (x // 32) % 2
    grain = 0.06 * np.sin(y / 3.0 + plank * 2.0)
    rgb = np.stack([0.45 + grain, 0.28 + grain * 0.7, 0.15 + grain * 0.4], -1)
    rgb *= np.where(plank[..., None] == 1, 0.9, 1.0)
    texture(wood, image("Planks", np.concatenate([rgb, np.ones((256, 256, 1))], -1)),
            "Base Color")  # fmt: skip
    add("plane", "Floor", wood, (0, 0, 0), size=1.0).scale = (6.0, 5.0, 1.0)
    ceiling = add("plane", "Ceiling", white, (0, 0, 3.0), size=1.0)
    ceiling.scale = (6.0, 5.0, 1.0)
    ceiling.rotation_euler = (math.pi, 0, 0)
    # Walls: boxes 0.1 m thick (+X, -X, +Y whole; -Y around the window).
    for name, loc, dims in (("WallE", (3.05, 0, 1.5), (0.1, 5.2, 3.0)),
                            ("WallW", (-3.05, 0, 1.5), (0.1, 5.2, 3.0)),
                            ("WallN", (0, 2.55, 1.5), (6.2, 0.1, 3.0)),
                            ("WallS_left", (-1.95, -2.55, 1.5), (2.3, 0.1, 3.0)),
                            ("WallS_right", (1.95, -2.55, 1.5), (2.3, 0.1, 3.0)),
                            ("WallS_below", (0, -2.55, 0.4), (1.6, 0.1, 0.8)),
                            ("WallS_above", (0, -2.55, 2.6), (1.6, 0.1, 0.8))):  # fmt: skip
        box = add("cube", name, white, loc, size=1.0)
        box.scale = dims
    sofa = add("cube", "Sofa", principled("Fabric", (0.3, 0.35, 0.5), 0.95), (-1.6, 1.6, 0.4),
               size=1.0)  # fmt: skip
    sofa.scale = (2.0, 0.9, 0.8)
    table = add("cube", "Table", principled("Lacquer", (0.05, 0.05, 0.05), 0.12),
                (0.6, 0.3, 0.37), size=1.0)  # fmt: skip
    table.scale = (1.2, 0.7, 0.06)
    sun = bpy.data.objects.new("Sun", bpy.data.lights.new("Sun", "SUN"))
    sun.data.energy = 4.0
    sun.data.angle = 0.0  # the farm's directional light is a delta
    sun.rotation_euler = (math.radians(55), 0.0, math.radians(15))  # down through the window
    bpy.context.scene.collection.objects.link(sun)
    camera((2.4, 1.9, 1.5), (-0.8, -1.0, 0.9), lens=20.0)
    return sky_map(with_sun=False)


def product_hdr():
    """A glass bottle, a brushed-metal can and two rough plastic blocks on a pale backdrop (a
    floor and a wall), lit only by the sky map and its small sun."""
    backdrop = principled("Backdrop", (0.75, 0.75, 0.72), 0.55)
    add("plane", "Floor", backdrop, (0, 0, 0), size=8.0)
    wall = add("plane", "Wall", backdrop, (0, 2.0, 2.0), size=8.0)
    wall.rotation_euler = (math.pi / 2, 0, 0)
    # Each object stands 1 mm above the floor: a glass bottom on the floor's plane would be
    # two coincident surfaces, which renderers resolve each their own way.
    bpy.ops.mesh.primitive_cylinder_add(vertices=64, radius=0.28, depth=1.0,
                                        location=(-0.6, 0.0, 0.501))  # fmt: skip
    bottle = bpy.context.active_object
    bottle.name = "Bottle"
    bottle.data.materials.append(glass_material(False))
    # Smooth sides, flat caps (sharp edges past 30 degrees), as a modeller shades a cylinder:
    # smooth caps bend their normals 45 degrees at the rim.
    bpy.ops.object.shade_smooth_by_angle(angle=math.radians(30))
    bpy.ops.mesh.primitive_cylinder_add(vertices=64, radius=0.25, depth=0.6,
                                        location=(0.35, 0.2, 0.301))  # fmt: skip
    can = bpy.context.active_object
    can.name = "Can"
    can.data.materials.append(principled("Brushed", (0.9, 0.9, 0.92), 0.3, metallic=1.0,
                                         **{"Anisotropic": 0.7}))  # fmt: skip
    bpy.ops.object.shade_smooth_by_angle(angle=math.radians(30))
    for name, loc, colour in (("BlockRed", (1.1, -0.3, 0.201), (0.7, 0.1, 0.08)),
                              ("BlockTeal", (-1.3, 0.5, 0.201), (0.1, 0.5, 0.5))):  # fmt: skip
        block = add("cube", name, principled(name, colour, 0.6), loc, size=0.4)
        block.rotation_euler = (0, 0, 0.4)
    camera((0.0, -4.2, 1.3), (0.0, 0.0, 0.45), lens=45.0)
    return sky_map()


def anisotropy():
    """KHR_materials_anisotropy as Blender's exporter writes it from a Principled BSDF:
    Anisotropic is anisotropyStrength, Anisotropic Rotation (turns) x 2 pi is
    anisotropyRotation, no texture; the importer sets the two sockets back and leaves Tangent
    unlinked, so Cycles takes its default tangent (radial about the object's Z axis). The
    exporter writes no TANGENT (the add-on's options), so the farm takes the tangent of
    TEXCOORD_0: on a UV sphere about Z both run along the parallels. Left: brushed metal,
    rotation 0 (roughened along the parallels); middle: the same turned 90 degrees (along the
    meridians); right: a black dielectric (its specular layer alone), rotation 0."""
    floor()
    steel = {"Anisotropic": 0.6}
    metal = {"color": (0.9, 0.85, 0.75), "roughness": 0.3, "metallic": 1.0}
    along = principled("BrushedAlong", **metal, **steel)
    across = principled("BrushedAcross", **metal, **steel, **{"Anisotropic Rotation": 0.25})
    black = principled("BrushedBlack", (0.0, 0.0, 0.0), 0.3, **steel)
    for i, mat in enumerate((along, across, black)):
        sphere(mat.name, mat, (-1.0 + 1.0 * i, 0.0, 0.42), radius=0.42)
    quad_light()
    point_light((2.5, -3.5, 3.0), 400.0)  # in front, to the right: a stretched highlight each
    camera((0.0, -5.0, 1.4), (0.0, 0.0, 0.42), lens=35.0)


def specular_color():
    """KHR_materials_specular's specularColorFactor as Blender's exporter writes it: Specular
    Tint (Specular IOR Level 0.5, so no specularFactor); the importer sets Specular Tint back,
    which Cycles applies to F0 (white at grazing angles), as the extension tints F0. Left: a
    black base (the specular layer alone); right: a white base (the diffuse under a coloured
    specular layer)."""
    floor()
    tint = {"Specular Tint": (1.0, 0.45, 0.1, 1.0)}
    sphere("TintedBlack", principled("TintedBlack", (0.0, 0.0, 0.0), 0.25, **tint),
           (-0.75, 0.0, 0.5), radius=0.5)  # fmt: skip
    sphere("TintedWhite", principled("TintedWhite", (0.8, 0.8, 0.8), 0.25, **tint),
           (0.75, 0.0, 0.5), radius=0.5)  # fmt: skip
    quad_light()
    point_light((-2.5, -3.0, 3.5), 400.0)
    camera()


def keyed(obj, path: str, first, last, frames=(1, 48)) -> None:
    """Keys obj.path at the shot's first and last frame (Blender's default Bezier easing)."""
    setattr(obj, path, first)
    obj.keyframe_insert(path, frame=frames[0])
    setattr(obj, path, last)
    obj.keyframe_insert(path, frame=frames[1])


def animated_shot():
    """The shot of tests/blender_pose_driver.py, lit and given materials: 48 frames at 24 fps
    with Blender's default Bezier easing. A camera dollies in from (0, -8, 3) to (1, -4.5, 2),
    aimed by a Track To constraint at an empty; a box turns (20 degrees about X, 180 about Z)
    and slides under a parent empty turning 40 degrees about Z; a cylinder (12 sides, 7
    segments) skinned to a two-bone armature whose upper bone bends 70 degrees about X and 30
    about Z. A grey floor, an emissive quad above and a point light to the front left, so that
    the moving silhouettes stand against the floor and cast shadows on it."""
    scene = bpy.context.scene
    first, last = ANIMATED["animated_shot"]["frames"]
    scene.render.fps, scene.render.fps_base = int(ANIMATED["animated_shot"]["fps"]), 1.0
    scene.frame_start, scene.frame_end = first, last
    # Square, as the harness renders: the exported yfov is the camera's at this aspect.
    scene.render.resolution_x = scene.render.resolution_y = 512
    floor(size=12.0)

    bpy.ops.object.empty_add(location=(0.5, 0, 0))
    pivot = bpy.context.object
    pivot.name = "Pivot"
    keyed(pivot, "rotation_euler", (0, 0, 0), (0, 0, math.radians(40)))
    box = add("cube", "Box", principled("White", (0.8, 0.8, 0.8), 0.5), (0, 0, 0.5), size=1.0)
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
    tube.data.materials.append(principled("Orange", (0.8, 0.3, 0.08), 0.5))
    bpy.ops.object.mode_set(mode="EDIT")
    bpy.ops.mesh.subdivide(number_cuts=6)
    bpy.ops.object.mode_set(mode="OBJECT")
    bpy.ops.object.select_all(action="DESELECT")
    tube.select_set(True)
    rig.select_set(True)
    bpy.context.view_layer.objects.active = rig
    bpy.ops.object.parent_set(type="ARMATURE_AUTO")
    bend = rig.pose.bones["Upper"]
    bend.rotation_mode = "XYZ"
    keyed(bend, "rotation_euler", (0, 0, 0), (math.radians(70), 0, math.radians(30)))

    quad_light((0.0, 0.0, 4.0), size=2.0, strength=6.0)
    point_light((-3.0, -3.0, 4.0), 400.0)
    bpy.ops.object.empty_add(location=(0, 0, 0.7))
    aim = bpy.context.object
    aim.name = "Aim"
    cam = camera((0, -8, 3), (0, 0, 0.7), lens=28.0)
    track = cam.constraints.new("TRACK_TO")
    track.target = aim
    keyed(cam, "location", (0, -8, 3), (1, -4.5, 2))


def export_animated(path: str) -> None:
    """The scene exported as the Blender add-on exports an animation (export_animation in
    integrations/blender/renderfarm_blender/export.py, imported from the source tree): its
    ANIMATION_OPTIONS (the timeline baked at every frame in SCENE mode, frame f at f / fps),
    the active camera kept; but without KHR_animation_pointer channels. Blender 5.0's exporter
    fails with them on a mesh that has a modifier and a material (here the skinned
    cylinder): with export_apply it exports the evaluated mesh's copy of the material, then
    looks for that copy among bpy.data.materials by id() when it samples material pointers,
    and does not find it (IndexError in scene_animation.gather_scene_animations). Nothing of
    this scene's data (camera lens, lights, materials) is animated, so no channel is lost."""
    sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "integrations",
                                    "blender"))  # fmt: skip
    from renderfarm_blender import export

    scene = bpy.context.scene
    options = {**export.ANIMATION_OPTIONS, "export_pointer_animation": False}
    result = bpy.ops.export_scene.gltf(filepath=path, **options)
    assert result == {"FINISHED"}, result
    with open(path, "rb") as f:
        glb = export.keep_only_camera(f.read(), scene.camera.name)
    with open(path, "wb") as f:
        f.write(glb)


def glb_document(path: str) -> dict:
    """The JSON chunk of a GLB file."""
    with open(path, "rb") as f:
        data = f.read()
    (length,) = struct.unpack_from("<I", data, 12)
    return json.loads(data[20 : 20 + length])


def save_hdr(rgb: np.ndarray, path: str) -> None:
    """A Radiance .hdr (flat RGBE scanlines, row 0 of rgb at the top), written here rather than
    through bpy: Blender saves a float image display-encoded, not as linear radiance."""
    h, w, _ = rgb.shape
    top = rgb.max(axis=-1)
    mantissa, exponent = np.frexp(top)
    scale = np.where(top > 1e-32, mantissa * 256.0 / np.maximum(top, 1e-32), 0.0)
    rgbe = np.zeros((h, w, 4), dtype=np.uint8)
    rgbe[..., :3] = np.clip(rgb * scale[..., None], 0, 255).astype(np.uint8)
    rgbe[..., 3] = np.where(top > 1e-32, exponent + 128, 0)
    with open(path, "wb") as f:
        f.write(f"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y {h} +X {w}\n".encode())
        f.write(rgbe.tobytes())


def build(name: str, path: str) -> dict:
    """Export scene name to path; {"scene": path, "environment": its map's path or None}.
    An animated scene is exported with its animation, as the add-on exports one."""
    empty_scene()
    env = globals()[name]()
    if name in ANIMATED:
        export_animated(path)
        if not glb_document(path).get("animations"):
            raise SystemExit(f"{name}: the add-on's export wrote no animation")
    else:
        result = bpy.ops.export_scene.gltf(filepath=path, **EXPORT_OPTIONS)
        assert result == {"FINISHED"}, result
    if name in REQUIRED_EXTENSIONS:
        extension = REQUIRED_EXTENSIONS[name]
        document = glb_document(path)
        on = [m.get("name") for m in document.get("materials", [])
              if extension in m.get("extensions", {})]  # fmt: skip
        if extension not in document.get("extensionsUsed", []) or not on:
            raise SystemExit(f"{name}: Blender's exporter wrote no {extension}")
    written = {"scene": path, "environment": None}
    if env is not None:
        written["environment"] = os.path.splitext(path)[0] + "-environment.hdr"
        save_hdr(env, written["environment"])
    return written


if __name__ == "__main__":
    out_dir, names = sys.argv[1], sys.argv[2:]
    unknown = [n for n in names if n not in SCENES]
    if unknown:
        raise SystemExit(f"unknown parity scene(s) {unknown}; known: {sorted(SCENES)}")
    os.makedirs(out_dir, exist_ok=True)
    written = {}
    for name in names:
        written[name] = build(name, os.path.join(out_dir, f"{name}.glb"))
    print("RESULT " + json.dumps(written), flush=True)
