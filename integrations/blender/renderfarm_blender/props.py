"""The add-on's data: preferences (farm URL, API token, CA file: never in a .blend) and, per
scene, the job settings built from the farm's list, the scene check and the jobs submitted."""

from __future__ import annotations

import json
import os

import bpy
from bpy.props import (
    BoolProperty,
    CollectionProperty,
    EnumProperty,
    FloatProperty,
    IntProperty,
    PointerProperty,
    StringProperty,
)

from . import export, jobsettings

DEFAULT_URL = "http://127.0.0.1:8080"


class RenderfarmPreferences(bpy.types.AddonPreferences):
    # Preferences live in Blender's user preferences (userpref.blend), not in the .blend files
    # artists save and share: the API token is a secret.
    bl_idname = __package__

    url: StringProperty(
        name="Farm URL",
        description="The farm's REST API, e.g. http://127.0.0.1:8080 or https://farm.example:8080",
        default=DEFAULT_URL,
    )
    token: StringProperty(
        name="API token",
        description="The token from `renderfarm token create NAME`; empty uses $RENDERFARM_TOKEN, "
        "or none on a local farm without tokens. Kept in the preferences, never in the .blend",
        subtype="PASSWORD",
    )
    ca_file: StringProperty(
        name="CA file",
        description="PEM file of the CA an https farm's certificate is checked against; empty uses "
        "$RENDERFARM_CA_FILE or the system's CAs",
        subtype="FILE_PATH",
    )
    timeout_s: FloatProperty(
        name="Timeout (s)",
        description="Seconds a request to the farm may take to connect, send and answer",
        default=60.0,
        min=1.0,
        max=3600.0,
    )

    def draw(self, context):
        layout = self.layout
        layout.prop(self, "url")
        layout.prop(self, "token")
        layout.prop(self, "ca_file")
        layout.prop(self, "timeout_s")


def preferences(context=None) -> RenderfarmPreferences:
    context = context or bpy.context
    return context.preferences.addons[__package__].preferences


def farm_url(scene, context=None) -> str:
    override = scene.renderfarm.url_override.strip()
    return override or preferences(context).url.strip()


def farm_credentials(context=None) -> tuple[str, str, float]:
    """(token, CA file, timeout): the preferences, else $RENDERFARM_TOKEN / $RENDERFARM_CA_FILE
    as the command-line client reads them."""
    prefs = preferences(context)
    token = prefs.token.strip() or os.environ.get("RENDERFARM_TOKEN", "")
    ca_file = (
        bpy.path.abspath(prefs.ca_file)
        if prefs.ca_file
        else os.environ.get("RENDERFARM_CA_FILE", "")
    )
    return token, ca_file, prefs.timeout_s


# Enum items must stay referenced while Blender shows them (bpy keeps only pointers).
_enum_items: dict[str, list[tuple[str, str, str]]] = {}


def _choice_items(self, context):
    choices = json.loads(self.choices_json or "[]")
    key = self.name + "\0" + self.choices_json
    if key not in _enum_items:
        _enum_items[key] = [(c, c, "") for c in choices] or [("", "(none)", "")]
    return _enum_items[key]


def _get_choice(self):
    choices = json.loads(self.choices_json or "[]")
    return choices.index(self.str_value) if self.str_value in choices else 0


def _set_choice(self, index):
    choices = json.loads(self.choices_json or "[]")
    if 0 <= index < len(choices):
        self.str_value = choices[index]


def _variant_items(self, context):
    items = jobsettings.variant_choices(export.scene_variants())
    key = "\0variant\0" + json.dumps(items)
    if key not in _enum_items:
        _enum_items[key] = items
    return _enum_items[key]


def _get_variant(self):
    values = [value for value, _, _ in jobsettings.variant_choices(export.scene_variants())]
    return values.index(self.variant) if self.variant in values else 0


def _set_variant(self, index):
    values = [value for value, _, _ in jobsettings.variant_choices(export.scene_variants())]
    if 0 <= index < len(values):
        self.variant = values[index]


class RenderfarmSetting(bpy.types.PropertyGroup):
    """One job setting, as the farm described it; its value in the field of its type."""

    # `name` (the setting's name) comes from PropertyGroup.
    kind: StringProperty(description="int, float, str or bool, as the farm says")
    help: StringProperty()
    default_json: StringProperty(description="the farm's default, as JSON")
    choices_json: StringProperty(description="the choices of a str setting, as JSON; [] for text")
    int_value: IntProperty(name="Value")
    float_value: FloatProperty(name="Value", precision=4, step=1)
    str_value: StringProperty(name="Value")
    bool_value: BoolProperty(name="Value")
    choice: EnumProperty(name="Value", items=_choice_items, get=_get_choice, set=_set_choice)

    def value(self):
        if self.kind == "int":
            return self.int_value
        if self.kind == "float":
            return self.float_value
        if self.kind == "bool":
            return self.bool_value
        return self.str_value

    def set_value(self, value) -> None:
        if self.kind == "int":
            self.int_value = int(value)
        elif self.kind == "float":
            self.float_value = float(value)
        elif self.kind == "bool":
            self.bool_value = bool(value)
        else:
            self.str_value = str(value)

    def default(self):
        return json.loads(self.default_json)


class RenderfarmIssue(bpy.types.PropertyGroup):
    kind: StringProperty()
    owner: StringProperty()
    message: StringProperty()


class RenderfarmJob(bpy.types.PropertyGroup):
    """A job submitted from this scene, as last seen on the farm (`name` is the job's name)."""

    job_id: StringProperty()
    farm_url: StringProperty(description="the farm the job was submitted to")
    frame: IntProperty(description="the frame of a still; the first frame of a sequence")
    frames: StringProperty(description="a sequence's frames in the farm's syntax; empty: a still")
    variants: BoolProperty(description="a job of every material variant: one image each")
    fps: FloatProperty(description="a sequence's frames per second, as sent to the farm")
    frame_last: IntProperty(description="the last frame of a sequence")
    frames_total: IntProperty()
    frames_fetched: IntProperty(description="the frames of a sequence last fetched")
    frames_done: IntProperty()
    state: StringProperty(default="queued")
    message: StringProperty(description="the farm's error, or why the job cannot be followed")
    tiles_done: IntProperty()
    tiles_total: IntProperty()
    mean_spp: FloatProperty()
    error: FloatProperty(description="the image's relative error")
    noise_threshold: FloatProperty()
    eta_s: FloatProperty(default=-1.0)
    elapsed_s: FloatProperty()
    image_name: StringProperty(description="the Blender image its result was fetched into")
    image_path: StringProperty()

    def progress(self) -> float:
        if self.state == "completed":
            return 1.0
        if self.tiles_total:
            return self.tiles_done / self.tiles_total
        if (self.frames or self.variants) and self.frames_total:
            return self.frames_done / self.frames_total
        return 0.0

    def summary(self) -> str:
        text = f"{self.state}"
        if self.frames and self.frames_total:
            text += f", frames {self.frames_done}/{self.frames_total}"
        elif self.variants and self.frames_total:
            text += f", variants {self.frames_done}/{self.frames_total}"
        if self.tiles_total:
            text += f", tiles {self.tiles_done}/{self.tiles_total}, {self.mean_spp:.0f} spp"
        if self.state == "running" and self.eta_s >= 0:
            text += f", ETA {self.eta_s:.0f} s"
        return text


class RenderfarmSceneSettings(bpy.types.PropertyGroup):
    render_mode: EnumProperty(
        name="Render",
        description="What a submission renders",
        items=(
            ("STILL", "Still", "The current frame, as one image"),
            (
                "ANIMATION",
                "Animation",
                "The scene's frame range (Output properties: Frame Start, End and Step) as a "
                "sequence of frames, from one export with the animation baked",
            ),
        ),
        default="STILL",
    )
    variant: StringProperty(
        description="settings.variant as the Material variant menu set it: empty for the "
        "default materials, a variant's name, or all"
    )
    variant_menu: EnumProperty(
        name="Material variant",
        description="Which materials render: the scene's own, one of the material variants "
        "Blender's glTF exporter writes (glTF Material Variants), or all of them, one image "
        "each",
        items=_variant_items,
        get=_get_variant,
        set=_set_variant,
    )
    url_override: StringProperty(
        name="Farm URL (this scene)",
        description="A farm for this scene only; empty uses the add-on's preferences",
    )
    job_name: StringProperty(
        name="Job name",
        description="Name of the jobs; empty: the .blend's name, the scene's and the frame",
    )
    use_scene_resolution: BoolProperty(
        name="Scene resolution",
        description="Render at the scene's output resolution (Output properties, with its %) "
        "rather than the width and height below; the exported camera's field of view follows "
        "the scene's aspect ratio",
        default=True,
    )
    settings_json: StringProperty(description="the farm's settings list (GET /api/v1/settings)")
    settings_url: StringProperty(description="the farm the settings list came from")
    settings: CollectionProperty(type=RenderfarmSetting)
    issues: CollectionProperty(type=RenderfarmIssue)
    issues_checked: BoolProperty()
    jobs: CollectionProperty(type=RenderfarmJob)
    active_job: IntProperty(default=-1)
    status: StringProperty(description="the last message for the artist")

    def docs(self) -> list[dict]:
        return json.loads(self.settings_json) if self.settings_json else []

    def load_docs(self, docs: list[dict], url: str) -> None:
        """Fields for every setting of `docs`; values already set are kept where the setting
        still exists with the same type and (for choices) a valid value."""
        docs = jobsettings.check_docs(docs)
        kept = {s.name: (s.kind, s.value()) for s in self.settings}
        self.settings.clear()
        for d in docs:
            if d.get("derived"):  # filled in by the farm (from the scene), not chosen
                continue
            item = self.settings.add()
            item.name = d["name"]
            item.kind = d["type"]
            item.help = d["help"]
            item.default_json = json.dumps(d["default"])
            item.choices_json = json.dumps(jobsettings.choices(d))
            value = d["default"]
            if d["name"] in kept and kept[d["name"]][0] == d["type"]:
                value = kept[d["name"]][1]
                options = jobsettings.choices(d)
                if options and value not in options:
                    value = d["default"]
            item.set_value(value)
        self.settings_json = json.dumps(docs)
        self.settings_url = url

    def reset_settings(self) -> None:
        for s in self.settings:
            s.set_value(s.default())

    def job_settings(self, scene) -> dict:
        """What a submission sends: the settings changed from the farm's defaults, the scene's
        resolution when use_scene_resolution is on, for an animation the scene's frames and
        frame rate (ValueError if the farm renders stills only), and the Material variant
        chosen (ValueError when it cannot be sent: jobsettings.variant_setting)."""
        docs = self.docs()
        values = {s.name: s.value() for s in self.settings}
        for name in (*jobsettings.SEQUENCE, jobsettings.VARIANT):
            values.pop(name, None)
        if self.use_scene_resolution:
            for name in jobsettings.RESOLUTION:
                values.pop(name, None)
        out = jobsettings.changed(values, docs)
        if self.use_scene_resolution:
            r = scene.render
            width = max(1, round(r.resolution_x * r.resolution_percentage / 100))
            height = max(1, round(r.resolution_y * r.resolution_percentage / 100))
            out.update(jobsettings.scene_overrides(docs, width, height))
        if self.render_mode == "ANIMATION":
            frames = export.farm_frames(*export.frame_range(scene))
            out.update(jobsettings.sequence_overrides(docs, frames, export.exporter_fps(scene)))
        out.update(
            jobsettings.variant_setting(
                docs, self.variant, export.scene_variants(), self.render_mode == "ANIMATION"
            )
        )
        return out

    def current_job(self):
        if 0 <= self.active_job < len(self.jobs):
            return self.jobs[self.active_job]
        return None


CLASSES = (
    RenderfarmPreferences,
    RenderfarmSetting,
    RenderfarmIssue,
    RenderfarmJob,
    RenderfarmSceneSettings,
)


def register() -> None:
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.renderfarm = PointerProperty(type=RenderfarmSceneSettings)


def unregister() -> None:
    del bpy.types.Scene.renderfarm
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
