"""Job settings as the farm describes them (GET /api/v1/settings), without bpy.

The farm is the only authority on which settings exist, their types and defaults: the add-on
stores the list it fetched (per scene) and builds its fields from it, so a setting added to the
farm appears in Blender without a new add-on.
"""

from __future__ import annotations

import re
import struct
from typing import Any

KINDS = ("int", "float", "str", "bool")
# A farm that does not serve `choices` lists them at the end of the help ("sample generator:
# sobol, halton, stratified, independent").
_CHOICES = re.compile(r":\s*([a-z0-9_]+(?:,\s*[a-z0-9_]+)+)\s*$", re.IGNORECASE)
# Set from the Blender scene rather than by hand (see scene_overrides).
RESOLUTION = ("width", "height")
# Set by the add-on's Still / Animation choice: a still sends none of them, an animation sends
# the scene's frame range and frame rate (its export holds one animation, so `animation` stays
# empty: every animation plays).
SEQUENCE = ("frames", "fps", "animation")
# Set by the add-on's Material variant menu (variant_choices): the default materials, one of the
# scene's KHR_materials_variants variants by name, or "all" of them, one image each.
VARIANT = "variant"
ALL_VARIANTS = "all"


def variant_choices(names: list[str]) -> list[tuple[str, str, str]]:
    """The Material variant menu as (value of the setting, label, description): the default
    materials, each variant the export carries by its name (once each), and All variants when
    there are any. A variant named "all" is rendered only with All variants: the farm reads
    "all" as every variant, and the add-on names variants rather than indices (the exporter
    writes only the variants some mesh uses, so Blender's list and the file's indices differ)."""
    items = [("", "Default materials", "The scene's own materials, no variant")]
    seen = set()
    for name in names:
        if name in seen or name == ALL_VARIANTS:
            continue
        seen.add(name)
        items.append((name, name, f"The materials of the variant {name!r}"))
    if names:
        items.append((
            ALL_VARIANTS,
            "All variants",
            f"Every variant, one image each ({len(names)}: {', '.join(names)})",
        ))  # fmt: skip
    return items


def variant_setting(
    docs: list[dict[str, Any]], chosen: str, names: list[str], animation: bool
) -> dict[str, str]:
    """settings.variant for the menu's choice `chosen` ({} for the default materials); a
    ValueError says why it cannot be sent: the farm has no such setting, the scene's export no
    longer carries that variant, or All variants with Animation (the farm renders every
    variant as stills)."""
    if not chosen:
        return {}
    if VARIANT not in {d["name"] for d in docs}:
        raise ValueError("this farm does not render material variants: choose Default materials")
    if chosen not in {value for value, _, _ in variant_choices(names)}:
        carried = ", ".join(names) or "none"
        raise ValueError(
            f"the scene's export has no material variant {chosen!r} (it carries: {carried}); "
            "choose another in Material variant"
        )
    if chosen == ALL_VARIANTS and animation:
        raise ValueError(
            "All variants renders each variant as a still: choose Still, or one variant for "
            "an animation"
        )
    return {VARIANT: chosen}


def choices(doc: dict[str, Any]) -> list[str]:
    """The values of an enumerated setting: the farm's `choices` (a farm before they were
    served lists them at the end of the help); [] for free text."""
    if doc.get("type") != "str":
        return []
    served = doc.get("choices")
    if isinstance(served, list) and served and all(isinstance(c, str) for c in served):
        return list(served)
    m = _CHOICES.search(str(doc.get("help", "")))
    return [c.strip() for c in m.group(1).split(",")] if m else []


def check_docs(docs: Any) -> list[dict[str, Any]]:
    """The settings list as the farm sent it, checked: a ValueError says what is malformed."""
    if not isinstance(docs, list):
        raise ValueError("the farm's settings are not a list")
    out = []
    for i, d in enumerate(docs):
        if not isinstance(d, dict) or not isinstance(d.get("name"), str) or not d["name"]:
            raise ValueError(f"setting {i} of the farm has no name")
        if d.get("type") not in KINDS:
            raise ValueError(f"setting {d['name']} has an unknown type {d.get('type')!r}")
        default = d.get("default")
        if d["type"] == "str" and not isinstance(default, str):
            raise ValueError(f"setting {d['name']}: default {default!r} is not text")
        if d["type"] == "bool" and not isinstance(default, bool):
            raise ValueError(f"setting {d['name']}: default {default!r} is not true or false")
        if d["type"] in ("int", "float") and (
            isinstance(default, bool) or not isinstance(default, (int, float))
        ):
            raise ValueError(f"setting {d['name']}: default {default!r} is not a number")
        entry = {
            "name": d["name"],
            "type": d["type"],
            "default": default,
            "help": str(d.get("help", "")),
        }
        served = d.get("choices")
        if isinstance(served, list) and all(isinstance(c, str) for c in served):
            entry["choices"] = list(served)
        if d.get("derived") is True:  # filled in by the farm (from the scene), not chosen
            entry["derived"] = True
        out.append(entry)
    return out


def _single(x: float) -> float:
    return struct.unpack("<f", struct.pack("<f", x))[0]


def changed(values: dict[str, Any], docs: list[dict[str, Any]]) -> dict[str, Any]:
    """The settings that differ from the farm's defaults (the farm fills in the others, so a
    default it changes later applies to new jobs)."""
    out = {}
    for d in docs:
        name = d["name"]
        if name not in values:
            continue
        value, default = values[name], d["default"]
        if d["type"] == "float":
            # Blender keeps floats in single precision (0.02 reads back as 0.0199999996):
            # equal in single precision is unchanged, and a changed value is sent with the
            # 7 significant digits single precision holds (0.05, not 0.0500000007).
            if _single(float(value)) != _single(float(default)):
                out[name] = float(f"{float(value):.7g}")
        elif value != default:
            out[name] = value
    return out


def scene_overrides(docs: list[dict[str, Any]], width: int, height: int) -> dict[str, int]:
    """width and height from the scene's output resolution, when the farm has those settings:
    the exported camera's field of view follows the scene's aspect ratio."""
    names = {d["name"] for d in docs}
    return {k: v for k, v in (("width", width), ("height", height)) if k in names}


def sequence_overrides(docs: list[dict[str, Any]], frames: str, fps: float) -> dict[str, Any]:
    """frames and fps of an animation submission; ValueError when the farm has no `frames`
    setting (a farm that renders stills only)."""
    names = {d["name"] for d in docs}
    if "frames" not in names or "fps" not in names:
        raise ValueError(
            "this farm renders stills only (its settings have no frames and fps): "
            "choose Still, or update the farm"
        )
    return {"frames": frames, "fps": float(fps)}
