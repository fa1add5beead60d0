"""What of a scene the farm will not render: what Blender's glTF exporter drops, and what the
farm's renderer ignores of what it exports.

The lists below follow the exporter of Blender 5.0 (io_scene_gltf2: the nodes its material
export reads, the object and light types it writes) and the glTF features the farm's loader
implements (worker/src/scene/gltf_loader.cpp). Nothing is refused: the artist is told, and may still
submit.
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
    kind: str  # material, volume, hair, object, light, camera, world, render
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


def scan(scene) -> list[Issue]:
    """Everything the farm will not render of `scene` as Blender would, in a stable order."""
    issues: list[Issue] = []
    materials = []
    seen_materials = set()
    soft_lights = []
    for obj in sorted(scene.objects, key=lambda o: o.name):
        if obj.hide_render or all(c.hide_render for c in obj.users_collection):
            continue  # not exported (the export keeps renderable objects only)
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
    if scene.render.use_motion_blur:
        issues.append(
            Issue(
                "render",
                f"Scene '{scene.name}'",
                "motion blur is not rendered (the farm renders a still frame)",
            )
        )
    return issues
