"""The Render properties panel and the status bar's progress."""

from __future__ import annotations

import bpy

from . import export, jobsettings, operators, props

_STATE_ICONS = {
    "queued": "SORTTIME",
    "running": "RENDER_ANIMATION",
    "completed": "CHECKMARK",
    "failed": "ERROR",
    "cancelled": "CANCEL",
    "unknown": "QUESTION",
}
MAX_ISSUES_SHOWN = 12


def _draw_setting(layout, item, enabled: bool) -> None:
    row = layout.row(align=True)
    row.enabled = enabled
    label = item.name.replace("_", " ").capitalize()
    if item.kind == "int":
        row.prop(item, "int_value", text=label)
    elif item.kind == "float":
        row.prop(item, "float_value", text=label)
    elif item.kind == "bool":
        row.prop(item, "bool_value", text=label)
    elif item.choices_json not in ("", "[]"):
        row.prop(item, "choice", text=label)
    else:
        row.prop(item, "str_value", text=label)
    op = row.operator("renderfarm.setting_help", text="", icon="INFO", emboss=False)
    op.setting = item.name


def describe_submission(scene) -> list[str]:
    """What Submit renders, in the panel's words."""
    variant = scene.renderfarm.variant
    if variant == jobsettings.ALL_VARIANTS:
        names = export.scene_variants()
        return [
            f"Renders frame {export.frames_to_submit(scene)[0]} once per material variant: "
            f"{len(names)} image{'s' * (len(names) != 1)} ({', '.join(names)})"
        ]
    if scene.renderfarm.render_mode != "ANIMATION":
        what = f" in the variant {variant!r}" if variant else ""
        return [f"Renders the current frame only (frame {export.frames_to_submit(scene)[0]}){what}"]
    first, last, step = export.frame_range(scene)
    count = export.frame_count(first, last, step)
    every = f", every {step}" if step > 1 else ""
    farm = export.farm_frames(first, last, step)
    lines = [
        f"Renders frames {first}-{last}{every}: {count} frame{'s' * (count != 1)} "
        f"at {export.playback_fps(scene):.4g} fps (farm frames {farm})"
    ]
    if abs(export.exporter_fps(scene) - export.playback_fps(scene)) > 1e-6:
        lines.append(
            f"The glTF export times frames at {export.exporter_fps(scene):.4g} fps: the farm "
            "renders Blender's frames, its preview movie plays at that rate"
        )
    return lines


class RENDER_PT_renderfarm(bpy.types.Panel):
    bl_label = "Render Farm"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "render"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        scene = context.scene
        rf = scene.renderfarm
        prefs = props.preferences(context)

        col = layout.column()
        col.prop(prefs, "url")
        col.prop(prefs, "token")
        col.prop(rf, "url_override")

        box = layout.box()
        row = box.row()
        row.label(text="Job settings", icon="SETTINGS")
        row.operator("renderfarm.refresh_settings", text="Refresh settings", icon="FILE_REFRESH")
        if not rf.settings:
            box.label(text="Press Refresh settings (or submit) to get the farm's settings")
        else:
            box.prop(rf, "job_name")
            box.prop(rf, "use_scene_resolution")
            for item in rf.settings:
                if item.name in jobsettings.SEQUENCE or item.name == jobsettings.VARIANT:
                    continue  # set by Still / Animation and Material variant below
                resolution = item.name in jobsettings.RESOLUTION
                _draw_setting(box, item, not (resolution and rf.use_scene_resolution))
            box.operator("renderfarm.reset_settings", icon="LOOP_BACK")

        box = layout.box()
        row = box.row()
        row.label(text="Not rendered by the farm", icon="ERROR" if rf.issues else "INFO")
        row.operator("renderfarm.check_scene", icon="VIEWZOOM")
        if not rf.issues_checked:
            box.label(text="Not checked yet (Submit checks too)")
        elif not rf.issues:
            box.label(text="Nothing: the export carries the whole scene", icon="CHECKMARK")
        for issue in list(rf.issues)[:MAX_ISSUES_SHOWN]:
            box.label(text=f"{issue.owner}: {issue.message}")
        if len(rf.issues) > MAX_ISSUES_SHOWN:
            box.label(
                text=f"... and {len(rf.issues) - MAX_ISSUES_SHOWN} more "
                "(Submit reports them all in the Info log)"
            )

        col = layout.column()
        col.row().prop(rf, "render_mode", expand=True)
        col.prop(rf, "variant_menu")
        for line in describe_submission(scene):
            col.label(text=line)
        row = layout.row()
        row.scale_y = 1.3
        row.operator("renderfarm.submit", icon="EXPORT")

        entry = rf.current_job()
        if entry is not None:
            box = layout.box()
            box.label(
                text=f"{entry.name}  ({entry.job_id[:8]})",
                icon=_STATE_ICONS.get(entry.state, "QUESTION"),
            )
            box.progress(factor=entry.progress(), type="BAR", text=entry.summary())
            if entry.message:
                box.label(text=entry.message, icon="ERROR")
            row = box.row()
            row.operator("renderfarm.cancel", icon="CANCEL")
            row.operator("renderfarm.fetch", icon="IMAGE_DATA")
            if entry.image_name and entry.frames:
                user = operators.sequence_user(entry.frame, entry.frame_last)
                box.label(
                    text=f"Image sequence '{entry.image_name}': {entry.frames_fetched} of "
                    f"{entry.frames_total} frames",
                    icon="IMAGE",
                )
                box.label(
                    text=f"Image Editor sidebar > Image: Frames {user['frame_duration']}, "
                    f"Start {user['frame_start']}, Offset {user['frame_offset']}, Auto Refresh"
                )
            elif entry.image_name:
                box.label(text=f"Image '{entry.image_name}'", icon="IMAGE")
                box.operator("renderfarm.compositor", icon="NODE_COMPOSITING")
        if rf.status:
            layout.label(text=rf.status)


def draw_status_bar(self, context):
    scene = context.scene
    rf = getattr(scene, "renderfarm", None)
    entry = rf.current_job() if rf is not None else None
    if entry is None or entry.state not in ("queued", "running"):
        return
    self.layout.progress(
        factor=entry.progress(), type="RING", text=f"Farm: {entry.name} {entry.summary()}"
    )


CLASSES = (RENDER_PT_renderfarm,)
