"""Light groups (#40): the radiance of a job split by the light source it came from, one RGB
layer per group, the groups summing to the image.

A group is named by each emitting node of the rendered scene: a node with a
`KHR_lights_punctual` light, or whose mesh emits (a material with a nonzero `emissiveFactor`,
or one an animation may give one; `KHR_materials_unlit`, whose base colour is radiance; points
and lines, which without normals are unlit). The node's `extras.light_group` names its group if
it is a non-empty string, else its `name`, else `nodes[i]`; names keep letters, digits, `_` and
`-` (anything else becomes `_`, so EXR readers and compositors take them as layer names), and
nodes whose names agree share a group. The environment (settings.environment, or black) is one
more group, `environment`, always last.

The server finds the groups in the scene's glTF JSON when a job asking for them is submitted and
keeps them in the job's settings (`light_groups`: a JSON object of group name -> the indices of
its nodes, in layer order), which the workers read: each contribution of a path goes to the
group of the node it came from (a punctual light's node, an emissive triangle's, an unlit
surface's) or to the environment. Over-inclusion is harmless (a group that never lights anything
is a black layer); a worker refuses a task in which an emitting node has no group, rather than
render layers that do not sum to the image.
"""

from __future__ import annotations

import json
import re
from typing import Any

from ..errors import SettingsError
from .channels import ENVIRONMENT_GROUP

ENVIRONMENT = ENVIRONMENT_GROUP
# Groups a job may have, the environment's included: each adds 24 bytes a pixel (float64 RGB)
# on the server and 12 to every result; more are refused naming settings.aovs.
MAX_GROUPS = 32
_UNSAFE = re.compile(r"[^A-Za-z0-9_-]")


def group_name(node: dict[str, Any], index: int) -> str:
    """A node's light group: its extras.light_group, else its name, else nodes[i], with every
    character but letters, digits, `_` and `-` replaced by `_`."""
    extras = node.get("extras")
    name = extras.get("light_group") if isinstance(extras, dict) else None
    if not isinstance(name, str) or not name.strip():
        name = node.get("name")
    if not isinstance(name, str) or not name.strip():
        name = f"nodes[{index}]"
    return _UNSAFE.sub("_", name.strip())


def _list(value: Any) -> list:
    return value if isinstance(value, list) else []


def _dict(value: Any) -> dict:
    return value if isinstance(value, dict) else {}


def _emissive_materials(document: dict[str, Any]) -> set[int]:
    """Materials that may emit: a nonzero emissiveFactor, KHR_materials_unlit, or an emissive
    property some animation targets (KHR_animation_pointer)."""
    out = set()
    for i, m in enumerate(_list(document.get("materials"))):
        m = _dict(m)
        factor = m.get("emissiveFactor")
        if isinstance(factor, list) and any(isinstance(v, int | float) and v > 0 for v in factor):
            out.add(i)
        if "KHR_materials_unlit" in _dict(m.get("extensions")):
            out.add(i)
    for animation in _list(document.get("animations")):
        for channel in _list(_dict(animation).get("channels")):
            target = _dict(_dict(channel).get("target"))
            pointer = _dict(_dict(target.get("extensions")).get("KHR_animation_pointer"))
            match = re.fullmatch(r"/materials/(\d+)/(.*)", str(pointer.get("pointer", "")))
            if match and "emissive" in match.group(2):
                out.add(int(match.group(1)))
    return out


def _mesh_emits(mesh: dict[str, Any], emissive: set[int]) -> bool:
    for primitive in _list(mesh.get("primitives")):
        primitive = _dict(primitive)
        if primitive.get("mode", 4) in (0, 1, 2, 3):  # points and lines: unlit without normals
            return True
        materials = [primitive.get("material")]
        variants = _dict(_dict(primitive.get("extensions")).get("KHR_materials_variants"))
        materials += [_dict(m).get("material") for m in _list(variants.get("mappings"))]
        if any(isinstance(m, int) and m in emissive for m in materials):
            return True
    return False


def _rendered_nodes(document: dict[str, Any]) -> list[int]:
    """The nodes of the scene the farm renders (`scene`, else the first), in index order."""
    nodes = _list(document.get("nodes"))
    scenes = _list(document.get("scenes"))
    index = document.get("scene", 0)
    if not scenes:  # no scene: the loader renders every root
        return list(range(len(nodes)))
    scene = _dict(scenes[index] if isinstance(index, int) and 0 <= index < len(scenes) else {})
    seen: set[int] = set()
    stack = [n for n in _list(scene.get("nodes")) if isinstance(n, int)]
    while stack:
        n = stack.pop()
        if n in seen or not 0 <= n < len(nodes):
            continue
        seen.add(n)
        stack.extend(c for c in _list(_dict(nodes[n]).get("children")) if isinstance(c, int))
    return sorted(seen)


def scene_groups(document: dict[str, Any]) -> dict[str, list[int]]:
    """The light groups of a glTF document: group name -> its nodes, in order of their first
    node, the environment last (with no node)."""
    nodes = _list(document.get("nodes"))
    meshes = _list(document.get("meshes"))
    emissive = _emissive_materials(document)
    groups: dict[str, list[int]] = {}
    for i in _rendered_nodes(document):
        node = _dict(nodes[i])
        light = "KHR_lights_punctual" in _dict(node.get("extensions"))
        mesh = node.get("mesh")
        emits = isinstance(mesh, int) and 0 <= mesh < len(meshes)
        emits = emits and _mesh_emits(_dict(meshes[mesh]), emissive)
        if light or emits:
            groups.setdefault(group_name(node, i), []).append(i)
    environment = groups.pop(ENVIRONMENT, [])  # a node named so shares the environment's
    groups[ENVIRONMENT] = environment
    return groups


def encode(groups: dict[str, list[int]]) -> str:
    """The settings value of a job's groups: compact JSON, in layer order."""
    return json.dumps(groups, separators=(",", ":"))


def check_count(groups: dict[str, list[int]]) -> None:
    """SettingsError naming settings.aovs for a scene with more groups than MAX_GROUPS."""
    if len(groups) > MAX_GROUPS:
        raise SettingsError(
            "settings.aovs",
            f"settings.aovs names light_groups, and the scene has {len(groups)} light groups "
            f"(its emitting nodes and the environment), more than {MAX_GROUPS}: give nodes a "
            "shared extras.light_group to group them, or leave light_groups out",
        )
