"""The panel's buttons: refresh the settings, check the scene, submit, cancel, fetch."""

from __future__ import annotations

import os
import re
import tempfile

import bpy
from bpy.props import StringProperty

from . import export, jobsettings, props, scan, watch
from .client import FarmClient, FarmError


def _client(context) -> FarmClient:
    token, ca_file, timeout_s = props.farm_credentials(context)
    return FarmClient(props.farm_url(context.scene, context), token, ca_file, timeout_s)


def refresh_settings(context) -> None:
    """Fetch the farm's settings into the scene (raises FarmError or ValueError)."""
    client = _client(context)
    context.scene.renderfarm.load_docs(client.settings(), client.url)


def check_scene(scene) -> list[scan.Issue]:
    issues = scan.scan(scene, animation=scene.renderfarm.render_mode == "ANIMATION")
    rf = scene.renderfarm
    rf.issues.clear()
    for issue in issues:
        item = rf.issues.add()
        item.kind, item.owner, item.message = issue.kind, issue.owner, issue.message
    rf.issues_checked = True
    return issues


class RENDERFARM_OT_refresh_settings(bpy.types.Operator):
    bl_idname = "renderfarm.refresh_settings"
    bl_label = "Refresh settings"
    bl_description = "Fetch the job settings the farm offers, with their defaults"

    def execute(self, context):
        rf = context.scene.renderfarm
        try:
            refresh_settings(context)
        except (FarmError, ValueError) as e:
            rf.status = e.report() if isinstance(e, FarmError) else str(e)
            self.report({"ERROR"}, f"Render farm: {rf.status}")
            return {"CANCELLED"}
        rf.status = f"{len(rf.settings)} settings from {rf.settings_url}"
        self.report({"INFO"}, f"Render farm: {rf.status}")
        return {"FINISHED"}


class RENDERFARM_OT_reset_settings(bpy.types.Operator):
    bl_idname = "renderfarm.reset_settings"
    bl_label = "Reset to farm defaults"
    bl_description = "Set every job setting back to the farm's default"

    @classmethod
    def poll(cls, context):
        return len(context.scene.renderfarm.settings) > 0

    def execute(self, context):
        context.scene.renderfarm.reset_settings()
        return {"FINISHED"}


class RENDERFARM_OT_setting_help(bpy.types.Operator):
    bl_idname = "renderfarm.setting_help"
    bl_label = "Setting help"
    bl_options = {"INTERNAL"}

    setting: StringProperty()

    @classmethod
    def description(cls, context, properties):
        item = context.scene.renderfarm.settings.get(properties.setting)
        if item is None:
            return properties.setting
        return f"{item.name} ({item.kind}, default {item.default_json}): {item.help}"

    def execute(self, context):
        item = context.scene.renderfarm.settings.get(self.setting)
        if item is not None:
            self.report(
                {"INFO"}, f"{item.name} ({item.kind}, default {item.default_json}): {item.help}"
            )
        return {"FINISHED"}


class RENDERFARM_OT_check_scene(bpy.types.Operator):
    bl_idname = "renderfarm.check_scene"
    bl_label = "Check scene"
    bl_description = "List what the glTF export drops and what the farm does not render"

    def execute(self, context):
        issues = check_scene(context.scene)
        if issues:
            self.report(
                {"WARNING"}, f"Render farm: {len(issues)} thing(s) will not render as in Blender"
            )
        else:
            self.report({"INFO"}, "Render farm: everything in the scene is exported")
        return {"FINISHED"}


def _default_job_name(scene, what: str) -> str:
    blend = os.path.splitext(os.path.basename(bpy.data.filepath))[0] or "untitled"
    return f"{blend} {scene.name} {what}"


def _fail(op, rf, e) -> set:
    rf.status = e.report() if isinstance(e, FarmError) else str(e)
    op.report({"ERROR"}, f"Render farm: {rf.status}")
    return {"CANCELLED"}


class RENDERFARM_OT_submit(bpy.types.Operator):
    bl_idname = "renderfarm.submit"
    bl_label = "Submit to farm"
    bl_description = (
        "Export the scene with Blender's glTF exporter (the current frame, or for Animation "
        "the frame range with its animation baked) and submit it to the farm as a job"
    )

    @classmethod
    def poll(cls, context):
        return context.scene is not None

    def execute(self, context):
        scene = context.scene
        rf = scene.renderfarm
        if scene.camera is None:
            return _fail(self, rf, export.ExportError(f"scene '{scene.name}' has no active camera"))
        try:
            client = _client(context)
            if not rf.settings_json or rf.settings_url != client.url:
                rf.load_docs(client.settings(), client.url)  # first use on this farm
            settings = rf.job_settings(scene)
        except (FarmError, ValueError) as e:
            return _fail(self, rf, e)
        issues = check_scene(scene)
        for issue in issues:
            self.report({"WARNING"}, f"Not rendered by the farm: {issue.text()}")
        sequence = rf.render_mode == "ANIMATION"
        if sequence:
            first, last, step = export.frame_range(scene)
            what = f"frames {settings['frames']}"
            described = (
                f"frames {settings['frames']}, {export.frame_count(first, last, step)} frames "
                f"at {settings['fps']:g} fps"
            )
        else:
            first = scene.frame_current
            what = described = f"frame {first}"
        name = rf.job_name.strip() or _default_job_name(scene, what)
        notes: list[str] = []
        try:
            if sequence:
                glb, notes = export.export_animation_reporting(scene)
            else:
                glb = export.export_frame(scene, first)
            job = client.submit(glb, f"{bpy.path.clean_name(scene.name)}.glb", settings, name)
        except (export.ExportError, FarmError) as e:
            return _fail(self, rf, e)
        for note in notes:
            self.report({"WARNING"}, f"Render farm: {note}")
        entry = rf.jobs.add()
        entry.name = str(job.get("name") or name)
        entry.job_id = str(job["id"])
        entry.farm_url = client.url
        entry.frame = first
        entry.frame_last = last if sequence else first
        entry.frames = settings.get("frames", "") if sequence else ""
        entry.variants = settings.get(jobsettings.VARIANT) == jobsettings.ALL_VARIANTS
        entry.fps = settings.get("fps", 0.0) if sequence else 0.0
        watch.apply_job(entry, job)
        rf.active_job = len(rf.jobs) - 1
        watch.watch(client, entry.job_id)
        rf.status = f"submitted job {entry.job_id} ({described})"
        if issues:
            rf.status += f"; {len(issues)} thing(s) will not render as in Blender"
        self.report({"INFO"}, f"Render farm: {rf.status}")
        return {"FINISHED"}


def _job_client(context, entry) -> FarmClient:
    token, ca_file, timeout_s = props.farm_credentials(context)
    return FarmClient(entry.farm_url, token, ca_file, timeout_s)


class RENDERFARM_OT_cancel(bpy.types.Operator):
    bl_idname = "renderfarm.cancel"
    bl_label = "Cancel job"
    bl_description = "Cancel the job on the farm"

    @classmethod
    def poll(cls, context):
        entry = context.scene.renderfarm.current_job()
        return entry is not None and entry.state in ("queued", "running")

    def execute(self, context):
        entry = context.scene.renderfarm.current_job()
        try:
            watch.apply_job(entry, _job_client(context, entry).cancel(entry.job_id))
        except FarmError as e:
            self.report({"ERROR"}, f"Render farm: {e.report()}")
            return {"CANCELLED"}
        return {"FINISHED"}


def _safe_name(entry) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", entry.name).strip("._") or "job"


def _results_directory() -> str:
    """`renderfarm/` next to the saved .blend, else in the temporary directory."""
    if bpy.data.filepath:
        return os.path.join(os.path.dirname(bpy.data.filepath), "renderfarm")
    return os.path.join(tempfile.gettempdir(), "renderfarm")


def result_path(entry) -> str:
    """Where a still job's EXR is written: renderfarm/NAME-ID.exr."""
    return os.path.join(_results_directory(), f"{_safe_name(entry)}-{entry.job_id[:8]}.exr")


def sequence_path(entry, frame: int, digits: int) -> str:
    """Where a frame of a sequence job is written: renderfarm/NAME-ID/NAME_0001.exr, the frame
    number zero-padded to `digits` (Blender's #### convention, so Blender reads the files as an
    image sequence numbered by the scene's frames)."""
    safe = _safe_name(entry)
    directory = os.path.join(_results_directory(), f"{safe}-{entry.job_id[:8]}")
    return os.path.join(directory, f"{safe}_{frame:0{digits}d}.exr")


def variant_path(entry, index: int, name: str) -> str:
    """Where a material variant's image of a job of every variant is written:
    renderfarm/NAME-ID/NAME_2_Dark_blue.exr (its index, then its name made safe)."""
    safe = _safe_name(entry)
    directory = os.path.join(_results_directory(), f"{safe}-{entry.job_id[:8]}")
    variant = re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._")
    return os.path.join(directory, f"{safe}_{index}" + (f"_{variant}" if variant else "") + ".exr")


def sequence_user(first: int, last: int) -> dict:
    """The image-user settings (Image Editor sidebar > Image: Frames, Start, Offset) under which
    scene frame f shows the sequence's file of frame f, for files first..last: Blender shows
    file (f - Start + 1) + Offset while Start <= f < Start + Frames."""
    return {
        "frame_start": first,
        "frame_offset": first - 1,
        "frame_duration": last - first + 1,
        "use_auto_refresh": True,
    }


def _show_sequence(context, image, first: int, last: int) -> None:
    """Image Editors that show the image, or show nothing, show it as the sequence, following
    the scene's frame."""
    for window in getattr(context.window_manager, "windows", ()):
        for area in window.screen.areas:
            if area.type != "IMAGE_EDITOR":
                continue
            space = area.spaces.active
            if space.image is not None and space.image != image:
                continue
            space.image = image
            for key, value in sequence_user(first, last).items():
                setattr(space.image_user, key, value)
            area.tag_redraw()


def _write(path: str, data: bytes) -> None:
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "wb") as f:
        f.write(data)


class RENDERFARM_OT_fetch(bpy.types.Operator):
    bl_idname = "renderfarm.fetch"
    bl_label = "Fetch result"
    bl_description = (
        "Download the job's multi-layer EXR (colour, albedo, normal, variance, spp, error), or "
        "every finished frame's of a sequence, and open it as an image named after the job "
        "(an image sequence for Animation)"
    )

    @classmethod
    def poll(cls, context):
        entry = context.scene.renderfarm.current_job()
        return entry is not None and entry.state not in ("queued", "unknown")

    def execute(self, context):
        entry = context.scene.renderfarm.current_job()
        if entry.frames:
            return self.fetch_sequence(context, entry)
        if entry.variants:
            return self.fetch_variants(context, entry)
        path = result_path(entry)
        try:
            _write(path, _job_client(context, entry).image_exr(entry.job_id))
        except FarmError as e:
            self.report({"ERROR"}, f"Render farm: {e.report()}")
            return {"CANCELLED"}
        except OSError as e:
            self.report({"ERROR"}, f"Render farm: cannot write {path}: {e}")
            return {"CANCELLED"}
        image = bpy.data.images.get(entry.image_name) if entry.image_name else None
        if image is not None and bpy.path.abspath(image.filepath) == path:
            image.reload()
        else:
            image = bpy.data.images.load(path, check_existing=False)
            image.name = entry.name
        entry.image_name, entry.image_path = image.name, path
        partial = "" if entry.state == "completed" else f" (job {entry.state}: partial image)"
        self.report({"INFO"}, f"Render farm: image '{image.name}' from {path}{partial}")
        return {"FINISHED"}

    def fetch_sequence(self, context, entry):
        client = _job_client(context, entry)
        path = ""
        try:
            frames = client.frames(entry.job_id)
            numbers = [int(f["frame"]) for f in frames]
            done = [int(f["frame"]) for f in frames if f.get("state") == "done"]
            if not done:
                self.report(
                    {"ERROR"},
                    f"Render farm: no frame of the sequence is finished yet "
                    f"(0 of {len(numbers)} done)",
                )
                return {"CANCELLED"}
            digits = max(4, len(str(max(numbers))))
            for frame in done:
                path = sequence_path(entry, frame, digits)
                _write(path, client.frame_exr(entry.job_id, frame))
        except FarmError as e:
            self.report({"ERROR"}, f"Render farm: {e.report()}")
            return {"CANCELLED"}
        except OSError as e:
            self.report({"ERROR"}, f"Render farm: cannot write {path}: {e}")
            return {"CANCELLED"}
        first_path = sequence_path(entry, done[0], digits)
        image = bpy.data.images.get(entry.image_name) if entry.image_name else None
        if image is not None and os.path.dirname(bpy.path.abspath(image.filepath)) == (
            os.path.dirname(first_path)
        ):
            # Fetched before: the same image, its first file perhaps an earlier frame now.
            image.filepath = first_path
            image.reload()
        else:
            image = bpy.data.images.load(first_path, check_existing=False)
            image.name = entry.name
        image.source = "SEQUENCE"
        _show_sequence(context, image, numbers[0], numbers[-1])
        entry.image_name, entry.image_path = image.name, first_path
        entry.frames_fetched = len(done)
        partial = "" if len(done) == len(numbers) else f" ({len(numbers) - len(done)} not done yet)"
        self.report(
            {"INFO"},
            f"Render farm: image sequence '{image.name}', {len(done)} of {len(numbers)} frames "
            f"in {os.path.dirname(first_path)}{partial}",
        )
        return {"FINISHED"}

    def fetch_variants(self, context, entry):
        """A job of every material variant: each finished variant's EXR as an image named
        after the job and the variant ("shoe - Red")."""
        client = _job_client(context, entry)
        path, loaded, paths = "", [], []
        try:
            images = [f for f in client.frames(entry.job_id) if f.get("state") == "done"]
            for f in images:
                name = str(f.get("variant") or f["frame"])
                path = variant_path(entry, int(f["frame"]), name)
                _write(path, client.frame_exr(entry.job_id, int(f["frame"])))
                image = next(
                    (i for i in bpy.data.images if bpy.path.abspath(i.filepath) == path), None
                )
                if image is not None:
                    image.reload()
                else:
                    image = bpy.data.images.load(path, check_existing=False)
                    image.name = f"{entry.name} - {name}"
                loaded.append(image.name)
                paths.append(path)
        except FarmError as e:
            self.report({"ERROR"}, f"Render farm: {e.report()}")
            return {"CANCELLED"}
        except OSError as e:
            self.report({"ERROR"}, f"Render farm: cannot write {path}: {e}")
            return {"CANCELLED"}
        if not loaded:
            self.report({"ERROR"}, "Render farm: no material variant of the job is finished yet")
            return {"CANCELLED"}
        entry.image_name, entry.image_path = loaded[0], paths[0]
        entry.frames_fetched = len(loaded)
        self.report(
            {"INFO"},
            f"Render farm: {len(loaded)} of {entry.frames_total} material variants as images "
            f"{', '.join(repr(n) for n in loaded)}",
        )
        return {"FINISHED"}


# The Cryptomatte types the farm writes with settings.aovs naming cryptomatte (docs/usage.md,
# "Outputs"): layers {type}00 .. {type}02 of its EXR.
CRYPTO_TYPES = ("CryptoObject", "CryptoMaterial", "CryptoAsset")


def compositor_tree(scene):
    """The scene's compositor node group (Blender 5.0: scene.compositing_node_group); a new one
    with an Image output if the scene has none."""
    tree = getattr(scene, "compositing_node_group", None)
    if tree is None:
        tree = bpy.data.node_groups.new(f"{scene.name} compositing", "CompositorNodeTree")
        tree.interface.new_socket("Image", in_out="OUTPUT", socket_type="NodeSocketColor")
        scene.compositing_node_group = tree
    return tree


def load_passes(scene, image) -> dict:
    """The fetched EXR's passes in the scene's compositor, in a frame named after the image: an
    Image node with every pass as an output, and a Cryptomatte node (source Image) per type the
    EXR has, fed the colour. An empty compositor gets the colour at its output; one in use is
    left as it is. What was made: {"frame", "passes", "cryptomatte"}."""
    tree = compositor_tree(scene)
    frame = tree.nodes.new("NodeFrame")
    frame.label = f"Render farm: {image.name}"
    source = tree.nodes.new("CompositorNodeImage")
    source.image = image
    source.parent = frame
    source.location = (0, 0)
    passes = [o.name for o in source.outputs if o.enabled]
    made = []
    for i, type_name in enumerate(t for t in CRYPTO_TYPES if f"{t}00" in passes):
        node = tree.nodes.new("CompositorNodeCryptomatteV2")
        node.source = "IMAGE"
        node.image = image
        node.layer_name = type_name
        node.label = type_name
        node.parent = frame
        node.location = (320, -260 * i)
        tree.links.new(source.outputs[0], node.inputs["Image"])
        made.append(type_name)
    outputs = [n for n in tree.nodes if n.bl_idname == "NodeGroupOutput"]
    if not outputs:
        output = tree.nodes.new("NodeGroupOutput")
        output.location = (700, 0)
        outputs = [output]
    sockets = [s for s in outputs[0].inputs if s.type != "CUSTOM"]
    if sockets and not sockets[0].is_linked:
        tree.links.new(source.outputs[0], sockets[0])
    return {"frame": frame.name, "passes": passes, "cryptomatte": made}


class RENDERFARM_OT_compositor(bpy.types.Operator):
    bl_idname = "renderfarm.compositor"
    bl_label = "Load passes into compositor"
    bl_description = (
        "Add the fetched image's passes to the scene's compositor: an Image node with every "
        "pass (colour, albedo, normal, depth, ...), and a Cryptomatte node per Cryptomatte type "
        "the job rendered (settings.aovs naming cryptomatte), ready to pick mattes"
    )

    @classmethod
    def poll(cls, context):
        entry = context.scene.renderfarm.current_job()
        return entry is not None and bool(entry.image_name) and not entry.frames

    def execute(self, context):
        entry = context.scene.renderfarm.current_job()
        image = bpy.data.images.get(entry.image_name)
        if image is None:
            self.report({"ERROR"}, f"Render farm: image '{entry.image_name}' is gone; fetch again")
            return {"CANCELLED"}
        made = load_passes(context.scene, image)
        crypto = f", Cryptomatte {', '.join(made['cryptomatte'])}" if made["cryptomatte"] else ""
        self.report(
            {"INFO"},
            f"Render farm: {len(made['passes'])} passes of '{image.name}' in the compositor"
            f"{crypto}",
        )
        return {"FINISHED"}


CLASSES = (
    RENDERFARM_OT_refresh_settings,
    RENDERFARM_OT_reset_settings,
    RENDERFARM_OT_setting_help,
    RENDERFARM_OT_check_scene,
    RENDERFARM_OT_submit,
    RENDERFARM_OT_cancel,
    RENDERFARM_OT_fetch,
    RENDERFARM_OT_compositor,
)
