"""What of a scene the farm will not render: what Blender's glTF exporter drops, and what the
farm's renderer ignores of what it exports.

The lists below follow the exporter of Blender 5.0 (io_scene_gltf2: the nodes its material
export reads, the object and light types it writes) and the glTF features the farm's loader
implements (worker/src/scene/gltf_loader.cpp and the gltf_*.cpp beside it). Nothing is refused:
the artist is told, and may still submit.
"""

from __future__ import annotations

from dataclasses import dataclass

# Shader nodes the glTF exporter translates (or walks through) when they feed a material's
# surface: the Principled BSDF and what it reads from its inputs (image textures with their UV
# mapping, normal maps, Separate Color for packed metallic/roughness, Mix for a colour factor,
# Math for factors and alpha clipping, values, colours, vertex colours), Emission, and the unlit
# patterns (Background, Mix Shader with Transparent BSDF and Light Path). Groups and reroutes are
# looked through.
EXPORTED_NODES = frozenset(
    {
        "ShaderNodeOutputMaterial",
        "ShaderNodeBsdfPrincipled",
        "ShaderNodeEmission",
        "ShaderNodeBackground",
        "ShaderNodeMixShader",
        "ShaderNodeBsdfTransparent",
        "ShaderNodeLightPath",
        "ShaderNodeTexImage",
        "ShaderNodeNormalMap",
        "ShaderNodeMapping",
        "ShaderNodeUVMap",
        "ShaderNodeSeparateColor",
        "ShaderNodeValue",
        "ShaderNodeRGB",
        "ShaderNodeVertexColor",
        "ShaderNodeAttribute",
        "ShaderNodeTangent",
        "ShaderNodeSeparateXYZ",
        "ShaderNodeVectorMath",
        "NodeReroute",
        "NodeGroupInput",
        "NodeGroupOutput",
    }
)
# Exported only in the forms the exporter documents.
_MATH_OPERATIONS = frozenset({"MULTIPLY", "ROUND", "SUBTRACT"})

# Principled BSDF inputs that change the look when above zero but that the export drops
# (no glTF extension for them) or that the farm does not render (it ignores the extension).
_PRINCIPLED_DROPPED = (
    ("Subsurface Weight", "subsurface scattering is not exported"),
    ("Diffuse Roughness", "diffuse roughness is not exported"),
    ("Thin Film Thickness", "thin film is not exported"),
    ("Anisotropic", "anisotropy is exported, but the farm does not render it"),
)

# Object types the exporter writes: meshes (modifiers applied), curves, surfaces and text
# (converted to meshes), cameras, lights, empties and armatures.
_OBJECT_TYPES_DROPPED = {
    "VOLUME": "Volume objects are not exported",
    "CURVES": "hair curves are not exported",
    "POINTCLOUD": "point clouds are not exported",
    "GREASEPENCIL": "Grease Pencil is not exported",
    "GPENCIL": "Grease Pencil is not exported",
    "META": "metaballs are not exported",
}


@dataclass(frozen=True)
class Issue:
    kind: str  # material, volume, hair, object, light, camera, world, render, animation
    owner: str  # the data-block's name, as the artist sees it in Blender
    message: str

    def text(self) -> str:
        return f"{self.owner}: {self.message}"


def _socket_in_use(socket) -> bool:
    """A float input that changes the look: linked, or a value above zero."""
    if socket is None:
        return False
    if socket.is_linked:
        return True
    value = getattr(socket, "default_value", 0.0)
    return isinstance(value, float) and value > 0.0


def _node_exported(node, from_socket_name: str) -> bool:
    idname = node.bl_idname
    if idname in EXPORTED_NODES:
        return True
    if idname == "ShaderNodeMath":
        return node.operation in _MATH_OPERATIONS
    if idname == "ShaderNodeMix":
        return node.data_type == "RGBA"
    if idname == "ShaderNodeMixRGB":  # the pre-3.4 colour mix, still found in old files
        return True
    if idname == "ShaderNodeTexCoord":
        return from_socket_name == "UV"
    return False


class _MaterialScan:
    def __init__(self, material):
        self.material = material
        self.issues: list[Issue] = []
        self.seen: set[tuple[int, str]] = set()
        self.reported: set[tuple[str, str]] = set()

    def add(self, kind: str, message: str) -> None:
        key = (kind, message)
        if key not in self.reported:
            self.reported.add(key)
            self.issues.append(Issue(kind, f"Material '{self.material.name}'", message))

    def walk_input(self, socket, where: str, group_stack: tuple) -> None:
        for link in socket.links:
            if link.is_muted or not link.is_valid:
                continue
            self.walk_node(link.from_node, link.from_socket, where, group_stack)

    def walk_node(self, node, from_socket, where: str, group_stack: tuple) -> None:
        key = (node.as_pointer(), from_socket.identifier if from_socket else "")
        if key in self.seen:
            return
        self.seen.add(key)
        if node.bl_idname == "NodeFrame":
            return
        if node.bl_idname == "ShaderNodeGroup" and node.node_tree is not None:
            if not node.mute:
                inner = node.node_tree
                out = next(
                    (
                        n
                        for n in inner.nodes
                        if n.bl_idname == "NodeGroupOutput" and n.is_active_output
                    ),
                    None,
                )
                out = out or next(
                    (n for n in inner.nodes if n.bl_idname == "NodeGroupOutput"), None
                )
                if out is not None:
                    target = next(
                        (
                            s
                            for s in out.inputs
                            if from_socket and s.identifier == from_socket.identifier
                        ),
                        None,
                    )
                    for s in [target] if target is not None else out.inputs:
                        self.walk_input(s, f"{where}group '{inner.name}' > ", group_stack + (node,))
                return
            for s in node.inputs:
                self.walk_input(s, where, group_stack)
            return
        if node.bl_idname == "NodeGroupInput" and group_stack:
            outer = group_stack[-1]
            target = next(
                (s for s in outer.inputs if from_socket and s.identifier == from_socket.identifier),
                None,
            )
            if target is not None:
                self.walk_input(target, where.rsplit("group '", 1)[0], group_stack[:-1])
            return
        if node.mute:  # a muted node passes its inputs through, as in Cycles
            for s in node.inputs:
                self.walk_input(s, where, group_stack)
            return
        label = node.label or node.name
        if (
            node.bl_idname.startswith("ShaderNodeVolume")
            or node.bl_idname == "ShaderNodeVolumePrincipled"
        ):
            self.add(
                "volume",
                f"{where}node '{label}' ({node.bl_label}): volumes are not rendered by the farm",
            )
            return
        if node.bl_idname in ("ShaderNodeBsdfHair", "ShaderNodeBsdfHairPrincipled"):
            self.add(
                "hair", f"{where}node '{label}' ({node.bl_label}): hair shading is not exported"
            )
            return
        if not _node_exported(node, from_socket.name if from_socket else ""):
            self.add(
                "material",
                f"{where}node '{label}' ({node.bl_label}) is not exported to glTF (Cycles only)",
            )
            return
        if node.bl_idname == "ShaderNodeBsdfPrincipled":
            self.check_principled(node, where)
        for s in node.inputs:
            self.walk_input(s, where, group_stack)

    def check_principled(self, node, where: str) -> None:
        for name, why in _PRINCIPLED_DROPPED:
            if _socket_in_use(node.inputs.get(name)):
                self.add("material", f"{where}{name}: {why}")
        transmission = node.inputs.get("Transmission Weight")
        if transmission is not None and transmission.is_linked:
            self.add(
                "material", f"{where}a texture on Transmission Weight is not rendered by the farm"
            )

    def run(self) -> list[Issue]:
        tree = self.material.node_tree
        if tree is None:
            return []
        output = tree.get_output_node("CYCLES") or tree.get_output_node("ALL")
        if output is None:
            return []
        surface = output.inputs.get("Surface")
        if surface is not None:
            self.walk_input(surface, "", ())
        volume = output.inputs.get("Volume")
        if volume is not None and volume.is_linked:
            node = volume.links[0].from_node
            self.add(
                "volume",
                f"volume shader '{node.label or node.name}' ({node.bl_label}): volumes are not "
                "rendered by the farm",
            )
        displacement = output.inputs.get("Displacement")
        if displacement is not None and displacement.is_linked:
            self.add("material", "displacement is not exported")
        return self.issues


def _world_issues(world) -> list[Issue]:
    if world is None:
        return []
    tree = world.node_tree
    lit = False
    if tree is not None:
        output = tree.get_output_node("CYCLES") or tree.get_output_node("ALL")
        surface = output.inputs.get("Surface") if output is not None else None
        if surface is not None and surface.is_linked:
            node = surface.links[0].from_node
            if node.bl_idname == "ShaderNodeBackground":
                color, strength = node.inputs["Color"], node.inputs["Strength"]
                lit = (
                    color.is_linked
                    or strength.is_linked
                    or (strength.default_value > 0 and max(color.default_value[:3]) > 0)
                )
            else:
                lit = True
    else:
        lit = max(world.color[:3]) > 0
    if not lit:
        return []
    return [
        Issue(
            "world",
            f"World '{world.name}'",
            "the background is not exported: the farm renders black unless the job's "
            "environment setting names an environment map",
        )
    ]


# What an animation export (export.ANIMATION_OPTIONS: "SCENE" mode, modifiers applied) carries
# and drops. It bakes every object's transform, every bone and the shape-key weights of meshes
# without modifiers at every frame, whatever moves them (keys, drivers, constraints, parents,
# rigid bodies). It writes each mesh once, evaluated at frame 0: a mesh whose modifiers change
# over time keeps its frame-0 shape, and a mesh with modifiers loses its shape keys (the
# evaluated mesh has none, so its shape-key animation does not play). Data animation is written
# as KHR_animation_pointer channels (export.py says which, and what the add-on puts right of
# them), which the farm renders: what changes is listed below only where the export does not
# carry it. Visibility and camera switches at markers have no glTF form in the export.

# Camera settings the export samples into perspective yfov (at the scene's aspect ratio),
# orthographic xmag / ymag and znear / zfar.
_CAMERA_CARRIED = frozenset(
    {
        "lens",
        "angle",
        "angle_x",
        "angle_y",
        "lens_unit",
        "sensor_width",
        "sensor_height",
        "sensor_fit",
        "ortho_scale",
        "clip_start",
        "clip_end",
    }
)
# Light settings written as intensity, color and the spot cones (cutoff_distance as range, when
# Custom Distance is on).
_LIGHT_CARRIED = frozenset({"energy", "color", "spot_size", "spot_blend"})
# Principled BSDF inputs whose animated value the export writes (unlinked, or fed by a Value
# node): Alpha only for a material that blends at frame 0 (alpha below 1 there).
_PRINCIPLED_CARRIED = frozenset(
    {
        "Base Color",
        "Metallic",
        "Roughness",
        "IOR",
        "Transmission Weight",
        "Coat Weight",
        "Coat Roughness",
        "Sheen Roughness",
        "Specular IOR Level",
        "Emission Color",
        "Emission Strength",
        "Anisotropic",
    }
)

# Modifiers that change the mesh from frame to frame by themselves (simulations and caches).
_TIME_MODIFIERS = {
    "CLOTH": "cloth simulation",
    "SOFT_BODY": "soft body simulation",
    "FLUID": "fluid simulation",
    "DYNAMIC_PAINT": "dynamic paint",
    "OCEAN": "ocean",
    "WAVE": "wave",
    "EXPLODE": "explode",
    "MESH_CACHE": "mesh cache",
    "MESH_SEQUENCE_CACHE": "mesh sequence cache",
    "PARTICLE_INSTANCE": "particle instance",
}
# Geometry-nodes nodes whose output follows the scene's time.
_TIME_NODES = frozenset(
    {"GeometryNodeInputSceneTime", "GeometryNodeSimulationInput", "GeometryNodeSimulationOutput"}
)


def _animated_paths(idblock) -> list[str]:
    """The data paths animated on an ID (keyframes of its action, NLA strips' actions, drivers)."""
    anim = getattr(idblock, "animation_data", None) if idblock is not None else None
    if anim is None:
        return []
    paths: list[str] = []
    actions = [anim.action] + [s.action for t in anim.nla_tracks for s in t.strips]
    for action in actions:
        if action is None:
            continue
        for fc in _action_fcurves(action, anim):
            paths.append(fc.data_path)
    paths.extend(d.data_path for d in anim.drivers)
    return list(dict.fromkeys(paths))


def _action_fcurves(action, anim):
    """An action's F-curves: a layered action's (Blender 4.4+) of the slot the ID uses, else the
    legacy list."""
    layers = getattr(action, "layers", None)
    if layers:
        slot = getattr(anim, "action_slot", None)
        for layer in layers:
            for strip in layer.strips:
                for bag in getattr(strip, "channelbags", ()):
                    if slot is None or bag.slot == slot:
                        yield from bag.fcurves
        return
    yield from getattr(action, "fcurves", ())


def _value_at(idblock, path: str, frame: float):
    """The animated path's value at `frame` from its F-curve (the first of an array's), or
    None without one."""
    anim = getattr(idblock, "animation_data", None)
    action = anim.action if anim is not None else None
    if action is None:
        return None
    for fc in _action_fcurves(action, anim):
        if fc.data_path == path:
            return fc.evaluate(frame)
    return None


def _material_path_carried(tree, path: str) -> bool:
    """Whether the export writes the animated node-tree path as a KHR_animation_pointer
    channel: an input of the Principled BSDF it maps (not linked: a linked input's value is
    unused), or a Value node's output feeding one."""
    owner, _, prop = path.rpartition(".")
    try:
        socket = tree.path_resolve(owner) if owner else None
    except ValueError:
        return False
    if socket is None or not hasattr(socket, "node") or prop != "default_value":
        return False
    node = socket.node
    if node.bl_idname == "ShaderNodeValue":
        return any(
            link.to_node.bl_idname == "ShaderNodeBsdfPrincipled"
            and link.to_socket.name in _PRINCIPLED_CARRIED
            for link in socket.links
        )
    if node.bl_idname != "ShaderNodeBsdfPrincipled" or socket.is_output or socket.is_linked:
        return False
    if socket.name == "Alpha":
        alpha = _value_at(tree, path, 0.0)
        return alpha is not None and alpha < 1.0
    return socket.name in _PRINCIPLED_CARRIED


def _moves(obj) -> bool:
    """The object's transform can change over the frames (keys, drivers, constraints)."""
    paths = _animated_paths(obj)
    transform = ("location", "rotation", "scale", "delta_", "matrix")
    return any(p.startswith(transform) for p in paths) or len(obj.constraints) > 0


def _tree_uses_time(tree, seen=None) -> bool:
    seen = set() if seen is None else seen
    if tree is None or tree.name in seen:
        return False
    seen.add(tree.name)
    for node in tree.nodes:
        if node.bl_idname in _TIME_NODES:
            return True
        if node.bl_idname == "GeometryNodeGroup" and _tree_uses_time(node.node_tree, seen):
            return True
    return bool(_animated_paths(tree))


def _socket_paths(tree, skip=None) -> list[str]:
    """A node tree's animated paths, a node's input named as the artist sees it
    (`Principled BSDF: Emission Strength` for nodes["Principled BSDF"].inputs[28].default_value),
    but those skip(tree, path) is true of."""
    named = []
    for path in _animated_paths(tree):
        if skip is not None and skip(tree, path):
            continue
        owner, _, prop = path.rpartition(".")
        try:
            socket = tree.path_resolve(owner) if owner else None
        except ValueError:
            socket = None
        if socket is not None and hasattr(socket, "node") and prop == "default_value":
            named.append(f"{socket.node.label or socket.node.name}: {socket.name}")
        else:
            named.append(path)
    return named


def _short(paths: list[str]) -> str:
    shown = ", ".join(paths[:3])
    return shown + (f" and {len(paths) - 3} more" if len(paths) > 3 else "")


def _animation_issues(scene, objects, materials) -> list[Issue]:
    issues: list[Issue] = []
    for obj in objects:
        owner = f"Object '{obj.name}'"
        paths = _animated_paths(obj)
        if any(p in ("hide_render", "hide_viewport") for p in paths):
            issues.append(
                Issue(
                    "animation",
                    owner,
                    "animated visibility is not exported: the object is shown (or hidden) on "
                    "every frame as at frame 0",
                )
            )
        modifiers = [m for m in getattr(obj, "modifiers", ()) if m.show_viewport]
        if obj.type == "MESH" and modifiers:
            key = obj.data.shape_keys
            if key is not None and _animated_paths(key):
                issues.append(
                    Issue(
                        "animation",
                        owner,
                        "shape keys of a mesh with modifiers are not exported (the export "
                        "applies the modifiers): its shape-key animation does not play",
                    )
                )
        why = []
        for m in modifiers:
            if m.type in _TIME_MODIFIERS:
                why.append(f"'{m.name}' ({_TIME_MODIFIERS[m.type]})")
            elif m.type == "NODES" and _tree_uses_time(m.node_group):
                why.append(f"'{m.name}' (geometry nodes using the scene time)")
            elif any(p.startswith(f'modifiers["{m.name}"]') for p in paths):
                why.append(f"'{m.name}' (animated settings)")
            elif m.type != "ARMATURE":
                for prop in m.bl_rna.properties:
                    if prop.type != "POINTER" or getattr(prop, "fixed_type", None) is None:
                        continue
                    if prop.fixed_type.identifier != "Object":
                        continue
                    other = getattr(m, prop.identifier, None)
                    if other is not None and other != obj and _moves(other):
                        why.append(f"'{m.name}' (follows '{other.name}', which moves)")
                        break
        if why:
            issues.append(
                Issue(
                    "animation",
                    owner,
                    f"modifier {', '.join(why)} changes the mesh over time: the export writes "
                    "the mesh once, as at frame 0 (only transforms, bones and shape keys animate)",
                )
            )
        if obj.type in ("LIGHT", "CAMERA") and (obj.type == "LIGHT" or obj == scene.camera):
            data = obj.data
            carried = _CAMERA_CARRIED if obj.type == "CAMERA" else _LIGHT_CARRIED
            if obj.type == "LIGHT" and data.use_custom_distance:
                carried = carried | {"cutoff_distance"}
            data_paths = [p for p in _animated_paths(data) if p not in carried]
            if obj.type == "LIGHT" and getattr(data, "node_tree", None) is not None:
                data_paths += _socket_paths(data.node_tree)
            if data_paths:
                what = "light" if obj.type == "LIGHT" else "camera"
                issues.append(
                    Issue(
                        "animation",
                        f"{what.capitalize()} '{obj.name}'",
                        f"the {what}'s animated settings ({_short(data_paths)}) are not exported: "
                        "every frame has them as at frame 0",
                    )
                )
    for mat in materials:
        mat_paths = _animated_paths(mat) + (
            _socket_paths(mat.node_tree, _material_path_carried) if mat.node_tree else []
        )
        if mat_paths:
            issues.append(
                Issue(
                    "animation",
                    f"Material '{mat.name}'",
                    f"animated material values ({_short(mat_paths)}) are not exported: every "
                    "frame has them as at frame 0",
                )
            )
    start, end = scene.frame_start, scene.frame_end
    bound = [m for m in scene.timeline_markers if m.camera is not None and m.frame <= end]
    if len({m.camera.name for m in bound}) > 1 or any(m.frame > start for m in bound):
        cam = scene.camera.name if scene.camera is not None else "the active camera"
        issues.append(
            Issue(
                "animation",
                f"Scene '{scene.name}'",
                f"camera switches at markers are not exported: every frame renders through '{cam}'",
            )
        )
    r = scene.render
    if abs(r.fps_base - 1.0) > 1e-6:
        issues.append(
            Issue(
                "animation",
                f"Scene '{scene.name}'",
                f"Blender plays {r.fps / r.fps_base:.4g} fps, but the glTF export times frames "
                f"at {r.fps * r.fps_base:.4g} fps: the farm renders Blender's frames, and its "
                "preview movie plays at the export's rate",
            )
        )
    return issues


def scan(scene, animation: bool = False) -> list[Issue]:
    """Everything the farm will not render of `scene` as Blender would, in a stable order;
    with `animation`, also what the animation export does not carry."""
    issues: list[Issue] = []
    exported = []
    materials = []
    seen_materials = set()
    soft_lights = []
    for obj in sorted(scene.objects, key=lambda o: o.name):
        if obj.hide_render or all(c.hide_render for c in obj.users_collection):
            continue  # not exported (the export keeps renderable objects only)
        exported.append(obj)
        if obj.type in _OBJECT_TYPES_DROPPED:
            kind = {"VOLUME": "volume", "CURVES": "hair"}.get(obj.type, "object")
            issues.append(Issue(kind, f"Object '{obj.name}'", _OBJECT_TYPES_DROPPED[obj.type]))
            continue
        for psys in getattr(obj, "particle_systems", ()):
            what = "hair" if psys.settings.type == "HAIR" else "particles"
            issues.append(
                Issue(
                    "hair" if what == "hair" else "object",
                    f"Object '{obj.name}'",
                    f"particle system '{psys.name}' ({what}) is not exported",
                )
            )
        if obj.type == "LIGHT":
            light = obj.data
            if light.type == "AREA":
                issues.append(
                    Issue(
                        "light",
                        f"Light '{obj.name}'",
                        "area lights are not exported (glTF has point, spot and sun lights)",
                    )
                )
            elif light.type in ("POINT", "SPOT") and light.shadow_soft_size > 0:
                soft_lights.append(obj.name)
        for slot in getattr(obj, "material_slots", ()):
            mat = slot.material
            if mat is not None and mat.name not in seen_materials:
                seen_materials.add(mat.name)
                materials.append(mat)
    for mat in sorted(materials, key=lambda m: m.name):
        issues.extend(_MaterialScan(mat).run())
    if soft_lights:
        names = ", ".join(f"'{n}'" for n in soft_lights)
        issues.append(
            Issue(
                "light",
                f"Lights {names}",
                "the radius (soft shadows) is not exported: point and spot lights are points",
            )
        )
    camera = scene.camera
    if camera is not None and camera.type == "CAMERA":
        cam = camera.data
        if cam.type == "PANO":  # the exporter writes perspective and orthographic cameras
            issues.append(
                Issue(
                    "camera",
                    f"Camera '{camera.name}'",
                    "panoramic cameras are not exported (perspective and orthographic only)",
                )
            )
        if cam.shift_x or cam.shift_y:
            issues.append(Issue("camera", f"Camera '{camera.name}'", "lens shift is not exported"))
        if cam.dof.use_dof:
            issues.append(
                Issue(
                    "camera",
                    f"Camera '{camera.name}'",
                    "depth of field is not exported: set aperture_radius and focus_distance in "
                    "the job settings",
                )
            )
    issues.extend(_world_issues(scene.world))
    if animation:
        issues.extend(_animation_issues(scene, exported, sorted(materials, key=lambda m: m.name)))
    if scene.render.use_motion_blur:
        issues.append(
            Issue(
                "render",
                f"Scene '{scene.name}'",
                "motion blur is not rendered (each frame is rendered at one instant)",
            )
        )
    return issues
