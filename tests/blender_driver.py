"""Runs inside Blender's Python (the bpy module of .venv-blender), started by
tests/test_blender_addon.py: installs the add-on from its zip as an artist would, builds a scene,
presses the add-on's buttons (operators) and prints what it saw as one JSON line `RESULT {...}`.
The test, in the project's own Python, checks that against the farm.

    python tests/blender_driver.py SCENARIO CONFIG.json

SCENARIO: `render` (settings, submit, follow, fetch, the Combined pass written as a plain EXR
by the compositor, the .blend saved), `scan` (a scene of things the farm does not render:
checked, submitted anyway, and exported with two cameras), `animation` (a moving box submitted
as Animation, followed, fetched as an image sequence read back frame by frame through the
compositor, and each frame submitted again as a Still), `animation_scan` (what the animation
export carries and drops, and its frame times, read from the .glb; no farm), `pointer` (a
light's power and the camera's lens keyed, exported as KHR_animation_pointer and submitted as
Animation) or `variants` (the
Material variant menu from the glTF exporter's variants, All variants submitted, followed and
fetched as an image per variant).
"""

from __future__ import annotations

import importlib
import json
import math
import os
import struct
import sys

# Blender's user resources (preferences, installed extensions) in the test's directory, never
# the user's own; read when bpy is imported, so set first.
CONFIG = json.loads(open(sys.argv[2]).read())
os.environ["BLENDER_USER_RESOURCES"] = CONFIG["user_resources"]

import bpy  # noqa: E402
from bpy_extras.object_utils import world_to_camera_view  # noqa: E402
from mathutils import Vector  # noqa: E402

# Run as a script, so tests/ is sys.path[0]: the tests' own waiting helper (stdlib only).
from waiting import wait_until  # noqa: E402

ADDON = "bl_ext.user_default.renderfarm"


def install_addon() -> None:
    result = bpy.ops.extensions.package_install_files(
        filepath=CONFIG["zip"], repo="user_default", enable_on_install=True
    )
    assert result == {"FINISHED"}, result
    assert ADDON in bpy.context.preferences.addons, list(bpy.context.preferences.addons.keys())


def module(name: str):
    return importlib.import_module(f"{ADDON}.{name}")


def empty_scene():
    """The start-up scene emptied (its cube, light and camera removed, no world)."""
    for obj in list(bpy.data.objects):
        bpy.data.objects.remove(obj)
    scene = bpy.context.scene
    scene.world = None
    return scene


def principled(name: str, color=(0.8, 0.8, 0.8), emission=0.0):
    mat = bpy.data.materials.new(name)
    nodes = mat.node_tree.nodes
    bsdf = nodes.get("Principled BSDF")
    if bsdf is None:  # an empty material tree: make the default pair
        nodes.clear()
        bsdf = nodes.new("ShaderNodeBsdfPrincipled")
        out = nodes.new("ShaderNodeOutputMaterial")
        mat.node_tree.links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
    bsdf.inputs["Base Color"].default_value = (*color, 1.0)
    if emission:
        bsdf.inputs["Emission Color"].default_value = (1.0, 1.0, 1.0, 1.0)
        bsdf.inputs["Emission Strength"].default_value = emission
    return mat


def mesh_object(scene, name: str, kind: str, size: float, location, material):
    if kind == "plane":
        bpy.ops.mesh.primitive_plane_add(size=size, location=location)
    else:
        bpy.ops.mesh.primitive_cube_add(size=size, location=location)
    obj = bpy.context.active_object
    obj.name = name
    obj.data.materials.append(material)
    return obj


def look_at(obj, target) -> None:
    direction = Vector(target) - obj.location
    obj.rotation_euler = direction.to_track_quat("-Z", "Y").to_euler()


def camera(scene, name: str, location, target):
    cam = bpy.data.objects.new(name, bpy.data.cameras.new(name))
    scene.collection.objects.link(cam)
    cam.location = location
    look_at(cam, target)
    return cam


def basic_scene(width: int, height: int):
    """A plane, a red cube, an emissive panel, a point light, a camera."""
    scene = empty_scene()
    mesh_object(scene, "Ground", "plane", 6.0, (0, 0, 0), principled("Grey"))
    mesh_object(scene, "Box", "cube", 1.0, (0, 0, 0.5), principled("Red", (0.8, 0.05, 0.05)))
    panel = mesh_object(scene, "Panel", "plane", 1.5, (0, 0, 2.8), principled("Glow", emission=4.0))
    panel.rotation_euler = (math.pi, 0, 0)  # facing down
    light = bpy.data.objects.new("Lamp", bpy.data.lights.new("Lamp", "POINT"))
    light.data.energy = 300.0
    light.data.shadow_soft_size = 0.0
    light.location = (2.0, -2.0, 3.0)
    scene.collection.objects.link(light)
    scene.camera = camera(scene, "Camera", (4.0, -4.0, 3.0), (0, 0, 0.5))
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    return scene


def run_op(op, **kwargs) -> dict:
    """An operator's outcome; an ERROR report raises in Blender without a window."""
    try:
        return {"result": sorted(op(**kwargs)), "error": ""}
    except RuntimeError as e:
        return {"result": ["CANCELLED"], "error": str(e)}


def set_setting(rf, name: str, value) -> None:
    item = rf.settings[name]
    if item.kind == "str" and json.loads(item.choices_json):
        item.choice = value
    else:
        item.set_value(value)


def combined_pass_to_exr(image, width: int, height: int, path: str) -> None:
    """The Combined pass of a multi-layer image, through the compositor into a plain 32-bit
    EXR: Blender's Python has no other way to read a multi-layer image's pixels."""
    scene = bpy.context.scene
    tree = bpy.data.node_groups.new("Read pass", "CompositorNodeTree")
    scene.compositing_node_group = tree
    node = tree.nodes.new("CompositorNodeImage")
    node.image = image
    tree.interface.new_socket("Image", in_out="OUTPUT", socket_type="NodeSocketColor")
    out = tree.nodes.new("NodeGroupOutput")
    tree.links.new(node.outputs["Combined"], out.inputs[0])
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    scene.render.filepath = path
    settings = scene.render.image_settings
    settings.file_format = "OPEN_EXR"
    settings.color_depth = "32"
    settings.color_mode = "RGB"
    bpy.ops.render.render(write_still=True)


def compositor_matte(width: int, height: int, path: str) -> dict:
    """The add-on's "Load passes into compositor" on a scene without a compositor, then the
    CryptoObject node it made picking the object Box, its Matte rendered into a plain EXR."""
    scene = bpy.context.scene
    scene.compositing_node_group = None
    out = {"op": run_op(bpy.ops.renderfarm.compositor)}
    tree = scene.compositing_node_group
    out["nodes"] = sorted(n.label or n.bl_idname for n in tree.nodes)
    crypto = next(n for n in tree.nodes if n.bl_idname == "CompositorNodeCryptomatteV2"
                  and n.layer_name == "CryptoObject")  # fmt: skip
    crypto.matte_id = "Box"
    output = next(n for n in tree.nodes if n.bl_idname == "NodeGroupOutput")
    out["output_was"] = [link.from_socket.name for link in output.inputs[0].links]
    tree.links.new(crypto.outputs["Matte"], output.inputs[0])
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.filepath = path
    settings = scene.render.image_settings
    settings.file_format = "OPEN_EXR"
    settings.color_depth = "32"
    settings.color_mode = "RGB"
    bpy.ops.render.render(write_still=True)
    return out


class CheckedLayout:
    """Stands in for bpy.types.UILayout when drawing the panel without a window: checks that
    every property drawn exists on its data, every operator is registered and every icon is
    one of Blender's, and records the text shown."""

    ICONS = set(bpy.types.UILayout.bl_rna.functions["prop"].parameters["icon"].enum_items.keys())

    def __init__(self, shown: list):
        self.shown = shown

    def _icon(self, kwargs) -> None:
        icon = kwargs.get("icon")
        assert icon is None or icon in self.ICONS, f"unknown icon {icon}"

    def __getattr__(self, name):  # attributes such as enabled, scale_y, use_property_split
        raise AttributeError(name)

    def __setattr__(self, name, value):
        object.__setattr__(self, name, value)

    def row(self, **_):
        return CheckedLayout(self.shown)

    column = box = row

    def label(self, text="", **kwargs):
        self._icon(kwargs)
        self.shown.append(text)

    def prop(self, data, name, **kwargs):
        self._icon(kwargs)
        assert name in data.bl_rna.properties, f"{data} has no property {name}"
        self.shown.append(kwargs.get("text") or data.bl_rna.properties[name].name)

    def operator(self, idname, **kwargs):
        self._icon(kwargs)
        category, op = idname.split(".")
        assert hasattr(getattr(bpy.ops, category), op), f"no operator {idname}"
        getattr(bpy.ops, category).__getattr__(op).get_rna_type()
        self.shown.append(kwargs.get("text", idname))
        return type("OpProps", (), {})()

    def progress(self, factor=0.0, type="BAR", text=""):
        assert 0.0 <= factor <= 1.0 and type in ("BAR", "RING")
        self.shown.append(text)


def draw_panel() -> list:
    panel = module("panel")
    shown: list = []
    fake = type("FakePanel", (), {})()
    fake.layout = CheckedLayout(shown)
    panel.RENDER_PT_renderfarm.draw(fake, bpy.context)
    panel.draw_status_bar(fake, bpy.context)
    return shown


def scenario_render() -> dict:
    out: dict = {}
    scene = basic_scene(CONFIG["width"], CONFIG["height"])
    prefs = bpy.context.preferences.addons[ADDON].preferences
    prefs.url = CONFIG["url"]
    rf = scene.renderfarm

    prefs.token = "not-the-token"
    out["wrong_token"] = run_op(bpy.ops.renderfarm.refresh_settings)
    prefs.token = CONFIG["token"]
    out["refresh"] = run_op(bpy.ops.renderfarm.refresh_settings)
    out["settings"] = [
        {
            "name": s.name,
            "type": s.kind,
            "default": s.default(),
            "help": s.help,
            "choices": json.loads(s.choices_json),
            "value": s.value(),
        }
        for s in rf.settings
    ]
    out["check"] = run_op(bpy.ops.renderfarm.check_scene)
    out["issues"] = [f"{i.owner}: {i.message}" for i in rf.issues]
    out["panel_before"] = draw_panel()

    set_setting(rf, "max_spp", -1)
    out["refused"] = run_op(bpy.ops.renderfarm.submit)
    out["jobs_after_refusal"] = len(rf.jobs)

    for name, value in CONFIG["settings"].items():
        set_setting(rf, name, value)
    rf.job_name = CONFIG["job_name"]
    out["submit"] = run_op(bpy.ops.renderfarm.submit)
    entry = rf.current_job()
    out["job_id"] = entry.job_id
    out["first_state"] = entry.state

    # Blender without a window runs no timers: call the add-on's timer function until the job
    # has finished, as Blender would every quarter of a second.
    watch = module("watch")
    seen_states = [entry.state]

    def finished():
        watch.apply_updates()
        entry = rf.current_job()
        if entry.state != seen_states[-1]:
            seen_states.append(entry.state)
        if entry.state == "running" and "panel_running" not in out:
            out["panel_running"] = draw_panel()
        return entry if entry.state in ("completed", "failed", "cancelled") else None

    entry = wait_until(finished, CONFIG["timeout_s"], "the job to finish")
    out["states"] = seen_states
    out["progress"] = {
        "tiles_done": entry.tiles_done,
        "tiles_total": entry.tiles_total,
        "mean_spp": entry.mean_spp,
        "summary": entry.summary(),
    }
    assert watch.wait_all(10), "a watcher still runs after its job finished"

    out["fetch"] = run_op(bpy.ops.renderfarm.fetch)
    image = bpy.data.images[entry.image_name]
    out["image"] = {
        "name": image.name,
        "path": bpy.path.abspath(image.filepath),
        "job_name": entry.name,
    }
    combined_pass_to_exr(image, CONFIG["width"], CONFIG["height"], CONFIG["combined_exr"])
    out["image"]["type"] = image.type  # known once Blender has read the file
    out["panel_after"] = draw_panel()
    if CONFIG.get("matte_exr"):
        out["compositor"] = compositor_matte(CONFIG["width"], CONFIG["height"],
                                             CONFIG["matte_exr"])  # fmt: skip

    # Uncompressed, so the test can search the bytes for the token.
    bpy.ops.wm.save_as_mainfile(filepath=CONFIG["blend"], compress=False)
    out["token_in_prefs"] = prefs.token == CONFIG["token"]
    return out


def scenario_scan() -> dict:
    out: dict = {}
    scene = basic_scene(16, 16)
    prefs = bpy.context.preferences.addons[ADDON].preferences
    prefs.url, prefs.token = CONFIG["url"], CONFIG["token"]

    # A material whose surface is Cycles' hair shader, one with a procedural texture inside a
    # node group, one with a volume shader and a coat.
    hair = bpy.data.materials.new("Fur")
    nodes, links = hair.node_tree.nodes, hair.node_tree.links
    nodes.clear()
    bsdf = nodes.new("ShaderNodeBsdfHair")
    bsdf.name = "Hair BSDF"
    out_node = nodes.new("ShaderNodeOutputMaterial")
    links.new(bsdf.outputs[0], out_node.inputs["Surface"])
    mesh_object(scene, "Furry", "cube", 0.5, (1.5, 0, 0.25), hair)

    group = bpy.data.node_groups.new("Marble", "ShaderNodeTree")
    group.interface.new_socket("Color", in_out="OUTPUT", socket_type="NodeSocketColor")
    noise = group.nodes.new("ShaderNodeTexNoise")
    noise.name = "Noise Texture"
    gout = group.nodes.new("NodeGroupOutput")
    group.links.new(noise.outputs["Color"], gout.inputs[0])
    marble = principled("Marbled")
    gnode = marble.node_tree.nodes.new("ShaderNodeGroup")
    gnode.node_tree = group
    marble.node_tree.links.new(
        gnode.outputs[0], marble.node_tree.nodes["Principled BSDF"].inputs["Base Color"]
    )
    marble.node_tree.nodes["Principled BSDF"].inputs["Anisotropic"].default_value = 0.5
    # Exported as KHR_materials_clearcoat, which the farm renders: not listed.
    marble.node_tree.nodes["Principled BSDF"].inputs["Coat Weight"].default_value = 0.5
    unused = marble.node_tree.nodes.new("ShaderNodeTexVoronoi")  # linked to nothing: harmless
    unused.name = "Unused Voronoi"
    mesh_object(scene, "Statue", "cube", 0.5, (-1.5, 0, 0.25), marble)

    fog = principled("Fog")
    vol = fog.node_tree.nodes.new("ShaderNodeVolumePrincipled")
    vol.name = "Fog Volume"
    out_fog = fog.node_tree.get_output_node("ALL")
    fog.node_tree.links.new(vol.outputs[0], out_fog.inputs["Volume"])
    mesh_object(scene, "FogBox", "cube", 0.5, (0, 1.5, 0.25), fog)

    smoke = bpy.data.objects.new("Smoke", bpy.data.volumes.new("Smoke"))
    scene.collection.objects.link(smoke)
    area = bpy.data.objects.new("Softbox", bpy.data.lights.new("Softbox", "AREA"))
    scene.collection.objects.link(area)
    grass = bpy.data.objects["Ground"]
    grass.modifiers.new("Grass", "PARTICLE_SYSTEM")
    grass.particle_systems[0].settings.type = "HAIR"
    hidden = bpy.data.objects.new("HiddenVolume", bpy.data.volumes.new("HiddenVolume"))
    hidden.hide_render = True  # not rendered by Blender either: not listed
    scene.collection.objects.link(hidden)

    # The active camera is made after another one, which the exporter writes first; the
    # other one is orthographic, which is not listed since it is not the active camera.
    scene.camera = camera(scene, "SideCam", (-4.0, 0.0, 1.0), (0, 0, 0.5))
    bpy.data.objects["Camera"].data.type = "ORTHO"

    out["check"] = run_op(bpy.ops.renderfarm.check_scene)
    out["issues"] = [
        {"kind": i.kind, "owner": i.owner, "message": i.message} for i in scene.renderfarm.issues
    ]
    export = module("export")
    glb = export.export_frame(scene, scene.frame_current)
    length = int.from_bytes(glb[12:16], "little")
    doc = json.loads(glb[20 : 20 + length])
    out["camera_nodes"] = [n["name"] for n in doc.get("nodes", []) if "camera" in n]
    out["exported_nodes"] = sorted(n.get("name", "") for n in doc.get("nodes", []))
    out["mesh_nodes"] = sorted(n.get("name", "") for n in doc.get("nodes", []) if "mesh" in n)

    rf = scene.renderfarm
    rf.load_docs(json.loads(CONFIG["settings_docs"]), CONFIG["url"])
    out["setting_fields"] = [s.name for s in rf.settings]
    for name, value in CONFIG["settings"].items():
        set_setting(rf, name, value)
    out["submit"] = run_op(bpy.ops.renderfarm.submit)
    out["job_id"] = rf.current_job().job_id if rf.current_job() else ""
    out["issues_after_submit"] = len(rf.issues)

    # Opened again, the .blend's unfinished job is followed again; then it is cancelled.
    watch = module("watch")
    watch.stop_all()
    entry = rf.current_job()
    entry.state = "running"  # as if saved while the job ran
    bpy.ops.wm.save_as_mainfile(filepath=CONFIG["blend"])
    bpy.ops.wm.open_mainfile(filepath=CONFIG["blend"])
    out["followed_after_open"] = watch.following()
    out["cancel"] = run_op(bpy.ops.renderfarm.cancel)
    out["state_after_cancel"] = bpy.context.scene.renderfarm.current_job().state
    watch.stop_all()
    return out


def read_glb(glb: bytes):
    """(JSON document, accessor reader) of a .glb: the reader gives an accessor's float
    elements as tuples (the exporter writes animation data as plain floats)."""
    length = int.from_bytes(glb[12:16], "little")
    doc = json.loads(glb[20 : 20 + length])
    binary = 20 + length + 8  # the BIN chunk's data, after its 8-byte header

    def accessor(index: int) -> list[tuple]:
        a = doc["accessors"][index]
        assert a["componentType"] == 5126, a  # FLOAT
        view = doc["bufferViews"][a["bufferView"]]
        width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}[a["type"]]
        start = binary + view.get("byteOffset", 0) + a.get("byteOffset", 0)
        flat = struct.unpack_from(f"<{a['count'] * width}f", glb, start)
        return [tuple(flat[i * width : (i + 1) * width]) for i in range(a["count"])]

    return doc, accessor


def keyframe(obj, path: str, frame: int, value, index: int = -1) -> None:
    """A key of obj.path at frame, interpolated linearly to its neighbours."""
    if index >= 0:
        getattr(obj, path)[index] = value
    else:
        setattr(obj, path, value)
    obj.keyframe_insert(path, index=index, frame=frame)


def moving_box_scene(width: int, height: int):
    """An emissive red box on black, its x keyed at frames 1, 2, 3 (-1.2, 0.0, 0.9: unequal
    steps, before frame 1 it stays at -1.2), a point light, a camera looking along +y."""
    scene = empty_scene()
    box = mesh_object(
        scene, "Mover", "cube", 0.8, (0, 0, 0.5), principled("Hot", (0.9, 0.1, 0.05), 6.0)
    )
    for frame, x in CONFIG["box_x"].items():
        keyframe(box, "location", int(frame), x, index=0)
    light = bpy.data.objects.new("Lamp", bpy.data.lights.new("Lamp", "POINT"))
    light.data.energy = 100.0
    light.data.shadow_soft_size = 0.0
    light.location = (0.0, -3.0, 3.0)
    scene.collection.objects.link(light)
    scene.camera = camera(scene, "Camera", (0.0, -6.0, 0.5), (0.0, 0.0, 0.5))
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    scene.frame_start, scene.frame_end, scene.frame_step = 1, 3, 1
    scene.render.fps, scene.render.fps_base = 24, 1.0
    scene.frame_set(2)  # the current frame is inside the range, and not its start
    return scene, box


def follow(rf, watch, what: str, timeout_s: float, seen: dict) -> None:
    """Run the add-on's timer until the current job finishes; draw the panel while it runs."""

    def finished():
        watch.apply_updates()
        entry = rf.current_job()
        if entry.state == "running" and "panel_running" not in seen:
            seen["panel_running"] = draw_panel()
        return entry.state in ("completed", "failed", "cancelled")

    wait_until(finished, timeout_s, what)


def sequence_frame_to_exr(image, frame: int, user: dict, width: int, height: int, path: str):
    """What Blender reads of an image sequence at scene frame `frame` under the image-user
    settings `user` (frame_start, frame_offset, frame_duration), through the compositor into a
    plain EXR."""
    scene = bpy.context.scene
    tree = bpy.data.node_groups.new("Read frame", "CompositorNodeTree")
    scene.compositing_node_group = tree
    node = tree.nodes.new("CompositorNodeImage")
    node.image = image
    node.frame_start, node.frame_offset = user["frame_start"], user["frame_offset"]
    node.frame_duration = user["frame_duration"]
    tree.interface.new_socket("Image", in_out="OUTPUT", socket_type="NodeSocketColor")
    out = tree.nodes.new("NodeGroupOutput")
    tree.links.new(node.outputs["Combined"], out.inputs[0])
    scene.frame_set(frame)
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.filepath = path
    settings = scene.render.image_settings
    settings.file_format = "OPEN_EXR"
    settings.color_depth = "32"
    settings.color_mode = "RGB"
    bpy.ops.render.render(write_still=True)


def scenario_animation() -> dict:
    out: dict = {}
    width, height = CONFIG["width"], CONFIG["height"]
    scene, box = moving_box_scene(width, height)
    prefs = bpy.context.preferences.addons[ADDON].preferences
    prefs.url, prefs.token = CONFIG["url"], CONFIG["token"]
    rf = scene.renderfarm
    out["refresh"] = run_op(bpy.ops.renderfarm.refresh_settings)
    for name, value in CONFIG["settings"].items():
        set_setting(rf, name, value)
    # Settings the artist typed into the farm's own frames / fps fields are not what is sent:
    # the Still / Animation choice is.
    set_setting(rf, "frames", "7-9")
    set_setting(rf, "fps", 12.0)
    rf.render_mode = "ANIMATION"
    rf.job_name = "moving box"
    out["panel_before"] = draw_panel()
    out["check"] = run_op(bpy.ops.renderfarm.check_scene)
    out["issues"] = [f"{i.owner}: {i.message}" for i in rf.issues]
    bpy.ops.wm.save_as_mainfile(filepath=CONFIG["blend"])  # results go next to it

    out["submit"] = run_op(bpy.ops.renderfarm.submit)
    out["frame_after_submit"] = scene.frame_current
    entry = rf.current_job()
    out["job_id"] = entry.job_id
    watch = module("watch")
    follow(rf, watch, "the sequence to finish", CONFIG["timeout_s"], out)
    entry = rf.current_job()
    out["progress"] = {
        "state": entry.state,
        "frames_done": entry.frames_done,
        "frames_total": entry.frames_total,
        "frames": entry.frames,
        "fps": entry.fps,
        "summary": entry.summary(),
    }
    out["panel_after"] = draw_panel()
    assert watch.wait_all(10), "a watcher still runs after its job finished"

    out["fetch"] = run_op(bpy.ops.renderfarm.fetch)
    image = bpy.data.images[entry.image_name]
    directory = os.path.dirname(bpy.path.abspath(image.filepath))
    out["image"] = {
        "name": image.name,
        "source": image.source,
        "path": bpy.path.abspath(image.filepath),
        "files": sorted(os.listdir(directory)),
    }
    out["panel_fetched"] = draw_panel()
    out["refetch"] = run_op(bpy.ops.renderfarm.fetch)  # again: the same image, reloaded
    out["images_after_refetch"] = sorted(i.name for i in bpy.data.images if i.source == "SEQUENCE")
    image = bpy.data.images[entry.image_name]
    # Blender's reading of the sequence at every scene frame, under the image-user settings
    # the files' numbering implies (files 1..3: the first at scene frame 1, no offset).
    count = CONFIG["frame_count"]
    out["read_back"] = {}
    for frame in range(1, count + 1):
        path = os.path.join(CONFIG["out_dir"], f"read_{frame}.exr")
        user = {"frame_start": 1, "frame_offset": 0, "frame_duration": count}
        sequence_frame_to_exr(image, frame, user, width, height, path)
        out["read_back"][frame] = path
    out["image"]["type"] = image.type  # known once Blender has read a frame
    # The add-on's image-user settings for a range that does not start at 1 (the panel's line
    # and the Image Editors it sets): the same files numbered 11..13 read at scene frames
    # 11..13.
    operators = module("operators")
    shifted = os.path.join(CONFIG["out_dir"], "shifted")
    os.makedirs(shifted)
    for frame in range(1, count + 1):
        name = os.path.join(directory, out["image"]["files"][frame - 1])
        with (
            open(name, "rb") as src,
            open(os.path.join(shifted, f"s_{frame + 10:04d}.exr"), "wb") as dst,
        ):
            dst.write(src.read())
    moved = bpy.data.images.load(os.path.join(shifted, "s_0011.exr"), check_existing=False)
    moved.source = "SEQUENCE"
    out["shifted_user"] = operators.sequence_user(11, 10 + count)
    out["shifted_read_back"] = {}
    for frame in range(1, count + 1):
        path = os.path.join(CONFIG["out_dir"], f"shifted_{frame}.exr")
        sequence_frame_to_exr(moved, frame + 10, out["shifted_user"], width, height, path)
        out["shifted_read_back"][frame] = path

    # Where Blender puts the box: its centre projected through the camera at every frame.
    out["projected"] = {}
    for frame in range(1, CONFIG["frame_count"] + 1):
        scene.frame_set(frame)
        p = world_to_camera_view(scene, scene.camera, box.matrix_world.translation)
        out["projected"][frame] = [p.x, p.y]

    # Each frame again as a Still, exported at that frame (export_current_frame).
    rf.render_mode = "STILL"
    out["stills"] = {}
    for frame in range(1, CONFIG["frame_count"] + 1):
        scene.frame_set(frame)
        rf.job_name = f"still {frame}"
        result = run_op(bpy.ops.renderfarm.submit)
        assert result["result"] == ["FINISHED"], result
        out["stills"][frame] = rf.current_job().job_id
        follow(rf, watch, f"the still of frame {frame}", CONFIG["timeout_s"], {})
    watch.stop_all()
    return out


def scenario_animation_scan() -> dict:
    """What the animation export carries (transforms baked whatever moves them, shape keys of a
    mesh without modifiers) and what it drops, as the scan lists it and as the .glb holds it."""
    out: dict = {}
    scene, box = moving_box_scene(16, 12)
    rf = scene.renderfarm
    rf.load_docs(json.loads(CONFIG["settings_docs"]), CONFIG["url"])
    grey = principled("Grey")

    follower = mesh_object(scene, "Follower", "cube", 0.3, (0, 2, 0), grey)
    constraint = follower.constraints.new("COPY_LOCATION")  # moves with the box, no keys
    constraint.target = box
    constraint.use_y = constraint.use_z = False

    blob = mesh_object(scene, "Blob", "cube", 0.5, (0, 3, 0), grey)
    blob.shape_key_add(name="Basis")
    up = blob.shape_key_add(name="Up")
    for v in up.data:
        v.co.z += 1.0
    keyframe(up, "value", 1, 0.0)
    keyframe(up, "value", 3, 1.0)

    lumpy = mesh_object(scene, "Lumpy", "cube", 0.5, (0, 4, 0), grey)
    lumpy.shape_key_add(name="Basis")
    up = lumpy.shape_key_add(name="Up")
    for v in up.data:
        v.co.z += 1.0
    keyframe(up, "value", 1, 0.0)
    keyframe(up, "value", 3, 1.0)
    lumpy.modifiers.new("Smooth", "SUBSURF")

    waver = mesh_object(scene, "Waver", "plane", 1.0, (2, 4, 0), grey)
    waver.modifiers.new("Ripple", "WAVE")
    still_mod = mesh_object(scene, "Beveled", "cube", 0.5, (-2, 4, 0), grey)
    still_mod.modifiers.new("Bevel", "BEVEL")  # a modifier that does not change over time

    clock = bpy.data.node_groups.new("Clock", "GeometryNodeTree")
    clock.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    clock.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    gin, gout = clock.nodes.new("NodeGroupInput"), clock.nodes.new("NodeGroupOutput")
    setpos = clock.nodes.new("GeometryNodeSetPosition")
    time = clock.nodes.new("GeometryNodeInputSceneTime")
    xyz = clock.nodes.new("ShaderNodeCombineXYZ")
    clock.links.new(gin.outputs[0], setpos.inputs["Geometry"])
    clock.links.new(time.outputs["Seconds"], xyz.inputs["Z"])
    clock.links.new(xyz.outputs[0], setpos.inputs["Offset"])
    clock.links.new(setpos.outputs[0], gout.inputs[0])
    ticker = mesh_object(scene, "Ticker", "cube", 0.5, (2, -2, 0), grey)
    ticker.modifiers.new("Clock", "NODES").node_group = clock

    blinker = mesh_object(scene, "Blinker", "cube", 0.5, (-2, -2, 0), grey)
    keyframe(blinker, "hide_render", 1, False)
    keyframe(blinker, "hide_render", 3, True)

    pulse = principled("Pulse", emission=1.0)
    strength = pulse.node_tree.nodes["Principled BSDF"].inputs["Emission Strength"]
    strength.default_value = 1.0
    strength.keyframe_insert("default_value", frame=1)
    strength.default_value = 5.0
    strength.keyframe_insert("default_value", frame=3)
    mesh_object(scene, "Pulsing", "cube", 0.3, (-2, 0, 2), pulse)

    tint = pulse.node_tree.nodes["Principled BSDF"].inputs["Sheen Tint"]  # not carried
    tint.default_value = (1.0, 1.0, 1.0, 1.0)
    tint.keyframe_insert("default_value", frame=1)
    tint.default_value = (1.0, 0.0, 0.0, 1.0)
    tint.keyframe_insert("default_value", frame=3)

    # Carried as KHR_animation_pointer: lens and power; not carried: f-stop and exposure.
    keyframe(scene.camera.data, "lens", 1, 50.0)
    keyframe(scene.camera.data, "lens", 3, 70.0)
    scene.camera.data.dof.aperture_fstop = 2.8
    scene.camera.data.dof.keyframe_insert("aperture_fstop", frame=1)
    scene.camera.data.dof.aperture_fstop = 5.6
    scene.camera.data.dof.keyframe_insert("aperture_fstop", frame=3)
    keyframe(bpy.data.objects["Lamp"].data, "energy", 1, 100.0)
    keyframe(bpy.data.objects["Lamp"].data, "energy", 3, 300.0)
    keyframe(bpy.data.objects["Lamp"].data, "exposure", 1, 0.0)
    keyframe(bpy.data.objects["Lamp"].data, "exposure", 3, 1.0)
    scene.frame_set(2)

    rf.render_mode = "STILL"
    run_op(bpy.ops.renderfarm.check_scene)
    out["still_issues"] = [
        {"kind": i.kind, "owner": i.owner, "message": i.message} for i in rf.issues
    ]
    rf.render_mode = "ANIMATION"
    out["check"] = run_op(bpy.ops.renderfarm.check_scene)
    out["issues"] = [{"kind": i.kind, "owner": i.owner, "message": i.message} for i in rf.issues]

    export = module("export")
    out["settings"] = rf.job_settings(scene)
    glb = export.export_animation(scene)
    out["frame_after_export"] = scene.frame_current
    doc, accessor = read_glb(glb)
    nodes = doc["nodes"]
    out["extensions"] = doc.get("extensionsUsed", [])
    out["animations"] = []
    for anim in doc.get("animations", []):
        channels = []
        for ch in anim["channels"]:
            sampler = anim["samplers"][ch["sampler"]]
            pointer = ch["target"].get("extensions", {}).get("KHR_animation_pointer", {})
            channels.append(
                {
                    "node": nodes[ch["target"]["node"]].get("name")
                    if "node" in ch["target"]
                    else pointer.get("pointer"),
                    "path": ch["target"]["path"],
                    "times": [t[0] for t in accessor(sampler["input"])],
                    "values": accessor(sampler["output"]),
                }
            )
        out["animations"].append({"name": anim.get("name"), "channels": channels})
    out["pulse_material"] = next(
        i for i, m in enumerate(doc["materials"]) if m.get("name") == "Pulse"
    )
    out["morphed_nodes"] = sorted(
        n["name"]
        for n in nodes
        if "mesh" in n and any("targets" in p for p in doc["meshes"][n["mesh"]]["primitives"])
    )
    out["exported_nodes"] = sorted(n.get("name", "") for n in nodes)
    out["camera_yfov"] = doc["cameras"][0]["perspective"]["yfov"]
    out["sensor_width"] = scene.camera.data.sensor_width
    # Blender's own world positions at every frame (z up), for the baked translations.
    out["world"] = {}
    for frame in (1, 2, 3):
        scene.frame_set(frame)
        out["world"][frame] = {
            name: list(bpy.data.objects[name].matrix_world.translation)
            for name in ("Mover", "Follower")
        }
    scene.frame_set(2)

    # A frame step, and a rate with fps_base (29.97 = 30 / 1.001): the settings sent, and the
    # times the exporter writes for them.
    scene.frame_end, scene.frame_step = 8, 3
    out["stepped_settings"] = rf.job_settings(scene)
    scene.frame_end, scene.frame_step = 3, 1
    scene.render.fps, scene.render.fps_base = 30, 1.001
    out["ntsc_settings"] = rf.job_settings(scene)
    out["ntsc_fps_base"] = scene.render.fps_base  # as Blender holds it (single precision)
    doc, accessor = read_glb(export.export_animation(scene))
    anim = doc["animations"][0]
    mover = next(i for i, n in enumerate(doc["nodes"]) if n.get("name") == "Mover")
    ch = next(c for c in anim["channels"] if c["target"] == {"node": mover, "path": "translation"})
    out["ntsc_times"] = [t[0] for t in accessor(anim["samplers"][ch["sampler"]]["input"])]
    run_op(bpy.ops.renderfarm.check_scene)
    out["ntsc_issues"] = [i.message for i in rf.issues if i.owner == f"Scene '{scene.name}'"]
    return out


def scenario_pointer() -> dict:
    """Data animation as an artist keys it: a point light's power and the camera's lens, over
    frames 1-3 (power 100, 400, 400 W; lens 50, 50, 25 mm), above a grey floor with a red
    emissive square, the camera looking straight down. Checked, exported (its .glb read back),
    submitted as Animation and followed to completion."""
    out: dict = {}
    scene = empty_scene()
    mesh_object(scene, "Floor", "plane", 12.0, (0, 0, 0), principled("Grey", (0.5, 0.5, 0.5)))
    square = principled("Square", (0.0, 0.0, 0.0))
    bsdf = square.node_tree.nodes["Principled BSDF"]
    bsdf.inputs["Emission Color"].default_value = (1.0, 0.0, 0.0, 1.0)
    bsdf.inputs["Emission Strength"].default_value = 1.0
    mesh_object(scene, "Square", "plane", 1.0, (0, 0, 0.01), square)
    lamp = bpy.data.objects.new("Lamp", bpy.data.lights.new("Lamp", "POINT"))
    lamp.data.shadow_soft_size = 0.0
    lamp.location = (0.0, 0.0, 3.0)
    scene.collection.objects.link(lamp)
    scene.camera = camera(scene, "Camera", (0.0, 0.0, 4.0), (0.0, 0.0, 0.0))
    for frame, (power, lens) in CONFIG["keys"].items():
        keyframe(lamp.data, "energy", int(frame), power)
        keyframe(scene.camera.data, "lens", int(frame), lens)
    scene.render.resolution_x, scene.render.resolution_y = CONFIG["width"], CONFIG["height"]
    scene.render.resolution_percentage = 100
    scene.frame_start, scene.frame_end, scene.frame_step = 1, len(CONFIG["keys"]), 1
    scene.render.fps, scene.render.fps_base = 24, 1.0
    scene.frame_set(1)

    prefs = bpy.context.preferences.addons[ADDON].preferences
    prefs.url, prefs.token = CONFIG["url"], CONFIG["token"]
    rf = scene.renderfarm
    out["refresh"] = run_op(bpy.ops.renderfarm.refresh_settings)
    for name, value in CONFIG["settings"].items():
        set_setting(rf, name, value)
    rf.render_mode = "ANIMATION"
    rf.job_name = "keyed light and lens"
    out["check"] = run_op(bpy.ops.renderfarm.check_scene)
    out["issues"] = [f"{i.owner}: {i.message}" for i in rf.issues]

    doc, accessor = read_glb(module("export").export_animation(scene))
    out["extensions"] = doc.get("extensionsUsed", [])
    out["light"] = doc["extensions"]["KHR_lights_punctual"]["lights"][0]
    out["pointers"] = {}
    for anim in doc["animations"]:
        for ch in anim["channels"]:
            ext = ch["target"].get("extensions", {}).get("KHR_animation_pointer")
            if ext is not None:
                sampler = anim["samplers"][ch["sampler"]]
                out["pointers"][ext["pointer"]] = {
                    "times": [t[0] for t in accessor(sampler["input"])],
                    "values": [v[0] for v in accessor(sampler["output"])],
                }
    # Blender's own values at every frame: the power, and the vertical field of view of the
    # image (the horizontal one is the camera's angle: the image is wider than high).
    out["blender"] = {}
    for frame in range(1, len(CONFIG["keys"]) + 1):
        scene.frame_set(frame)
        cam = scene.camera.data
        yfov = 2 * math.atan(math.tan(cam.angle / 2) * CONFIG["height"] / CONFIG["width"])
        out["blender"][frame] = {"energy": lamp.data.energy, "yfov": yfov}
    scene.frame_set(1)

    out["submit"] = run_op(bpy.ops.renderfarm.submit)
    entry = rf.current_job()
    out["job_id"] = entry.job_id
    watch = module("watch")
    follow(rf, watch, "the keyed sequence to finish", CONFIG["timeout_s"], out)
    watch.stop_all()
    return out


def emissive(name: str, color):
    """A material that shows its colour exactly: black, emitting `color` at strength 1."""
    mat = principled(name, (0.0, 0.0, 0.0))
    bsdf = mat.node_tree.nodes.get("Principled BSDF")
    bsdf.inputs["Emission Color"].default_value = (*color, 1.0)
    bsdf.inputs["Emission Strength"].default_value = 1.0
    return mat


def scenario_variants() -> dict:
    """Material variants made in the glTF exporter's own UI data (its Material Variants
    preference on): the Material variant menu offers the default materials, each variant a
    mesh uses and All variants; All variants with Animation is refused; All is submitted,
    followed and fetched as one image per variant. Then, with the preference off, the menu has
    the default materials only."""
    out: dict = {}
    scene = empty_scene()
    plane = mesh_object(scene, "Card", "plane", 20.0, (0, 0, 0), emissive("Red", (1, 0, 0)))
    scene.camera = camera(scene, "Camera", (0.0, 0.0, 3.0), (0, 0, 0))
    scene.render.resolution_x, scene.render.resolution_y = CONFIG["width"], CONFIG["height"]
    scene.render.resolution_percentage = 100
    gltf = bpy.context.preferences.addons["io_scene_gltf2"].preferences
    gltf.KHR_materials_variants_ui = True
    listed = bpy.data.scenes[0].gltf2_KHR_materials_variants_variants
    for i, (name, color) in enumerate(CONFIG["variants"]):
        variant = listed.add()
        variant.name, variant.variant_idx = name, i
        mapping = plane.data.gltf2_variant_mesh_data.add()
        mapping.material_slot_index = 0
        mapping.material = emissive(name, color)
        mapping.variants.add().variant.variant_idx = i
    unused = listed.add()  # no mesh maps a material to it: the exporter does not write it
    unused.name, unused.variant_idx = "Unused", len(CONFIG["variants"])

    prefs = bpy.context.preferences.addons[ADDON].preferences
    prefs.url, prefs.token = CONFIG["url"], CONFIG["token"]
    rf = scene.renderfarm
    out["refresh"] = run_op(bpy.ops.renderfarm.refresh_settings)
    props = module("props")
    out["menu"] = [[value, label] for value, label, _ in props._variant_items(rf, bpy.context)]
    out["default_variant"] = rf.variant_menu
    rf.variant_menu = CONFIG["variants"][1][0]
    out["one"] = rf.job_settings(scene).get("variant")
    for name, value in CONFIG["settings"].items():
        set_setting(rf, name, value)
    rf.variant_menu = "all"
    out["chosen"] = [rf.variant_menu, rf.variant]
    rf.render_mode = "ANIMATION"
    out["with_animation"] = run_op(bpy.ops.renderfarm.submit)
    rf.render_mode = "STILL"
    out["panel"] = draw_panel()
    rf.job_name = "cards"
    out["submit"] = run_op(bpy.ops.renderfarm.submit)
    entry = rf.current_job()
    out["job_id"] = entry.job_id
    watch = module("watch")
    follow(rf, watch, "the job of every variant", CONFIG["timeout_s"], out)
    out["summary"] = entry.summary()
    out["fetch"] = run_op(bpy.ops.renderfarm.fetch)
    out["images"] = {
        image.name: bpy.path.abspath(image.filepath)
        for image in bpy.data.images
        if image.name.startswith("cards - ")
    }
    watch.stop_all()
    gltf.KHR_materials_variants_ui = False
    out["menu_off"] = [[value, label] for value, label, _ in props._variant_items(rf, None)]
    return out


if __name__ == "__main__":
    install_addon()
    result = {
        "render": scenario_render,
        "scan": scenario_scan,
        "animation": scenario_animation,
        "animation_scan": scenario_animation_scan,
        "variants": scenario_variants,
        "pointer": scenario_pointer,
    }[sys.argv[1]]()
    print("RESULT " + json.dumps(result), flush=True)
