"""Render farm: submit the scene from Blender to a renderfarm server and fetch the result.

The panel is in Properties > Render > Render Farm. The farm is reached over its REST API with
the Python standard library only (client.py); the scene goes to the farm as a .glb written by
Blender's own glTF exporter (export.py); what the export or the farm leaves out is listed
before submitting (scan.py).
"""

from __future__ import annotations

import bpy
from bpy.app.handlers import persistent

from . import operators, panel, props, watch
from .client import FarmClient, FarmError


@persistent
def _resume_watching(_dummy=None) -> None:
    """After a .blend is opened, follow again the jobs its scenes submitted that had not
    finished when it was saved."""
    try:
        token, ca_file, timeout_s = props.farm_credentials()
    except KeyError:
        return
    for scene in bpy.data.scenes:
        for entry in scene.renderfarm.jobs:
            if entry.state in ("queued", "running") and entry.farm_url:
                try:
                    watch.watch(FarmClient(entry.farm_url, token, ca_file, timeout_s), entry.job_id)
                except FarmError as e:
                    entry.message = e.report()


@persistent
def _stop_watching(_dummy=None) -> None:
    watch.stop_all()


def register() -> None:
    props.register()
    for cls in operators.CLASSES + panel.CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.STATUSBAR_HT_header.append(panel.draw_status_bar)
    bpy.app.handlers.load_pre.append(_stop_watching)
    bpy.app.handlers.load_post.append(_resume_watching)


def unregister() -> None:
    watch.stop_all()
    if _resume_watching in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.remove(_resume_watching)
    if _stop_watching in bpy.app.handlers.load_pre:
        bpy.app.handlers.load_pre.remove(_stop_watching)
    bpy.types.STATUSBAR_HT_header.remove(panel.draw_status_bar)
    for cls in reversed(operators.CLASSES + panel.CLASSES):
        bpy.utils.unregister_class(cls)
    props.unregister()
