"""A USD stage as the farm's glTF: what a path tracer needs, converted by this code on usd-core.

`convert_stage(root_layer, root, work)` checks every asset path of every layer first
(usd_assets.check_layers: nothing outside the upload is opened or read), composes the stage and
writes one GLB, which then goes through the same acceptance as any upload (the workers' loader).
It runs in the conversion's child process (infra/usd_import.py) under CPU, memory and file-size
limits; nothing here imports usd-core at module level.

What converts (docs/scenes.md, "USD scenes", is the users' version):
- Units and axes: positions and translations are multiplied by metersPerUnit (glTF is in
  metres); a Z-up stage is turned to glTF's Y-up by a root node rotating -90 degrees about X.
- Transforms: each Xformable's local transformation (all xformOps) as its node's matrix;
  one with time samples as TRS and a channel of the glTF animation "usd"
  (transform_animation).
- Meshes: faces fan-triangulated (holes dropped), leftHanded orientation reversed, normals
  (primvars:normals or normals, any interpolation), every st-like primvar a material reads as
  TEXCOORD_n (v flipped), displayColor/displayOpacity as COLOR_0 where no material is bound;
  UsdGeomSubsets of the materialBind family as primitives of their own material. Cube,
  Sphere, Cylinder, Cone, Capsule and Plane gprims are tessellated. Subdivision surfaces
  render as their control cage (warned).
- Materials: usd_materials.py (UsdPreviewSurface).
- Instancing: an instanceable prim's prototype and a PointInstancer's prototypes are converted
  once; each instance is a node of its own using the same glTF meshes (the worker builds a
  shared mesh once and instances it).
- Skinning: a UsdSkel Skeleton's joints as nodes under its node (animated by its bound
  SkelAnimation), a glTF skin per skinned mesh (four influences a point), inverse bind
  matrices (geomBindTransform x bindTransform^-1)^T; dual-quaternion skinning is rendered as
  linear blend skinning (warned). Blend shapes are morph targets weighted by the
  SkelAnimation's blendShapeWeights (in-betweens and normal offsets warned).
- Deformation: points with time samples are a morph target per sample played by a weights
  channel; normals with time samples too are each target's NORMAL offsets. A topology that
  changes over time is a mesh per topology, each shown during its span by KHR_node_visibility
  animated through KHR_animation_pointer (topology_meshes).
- Cameras: UsdGeomCamera to a glTF camera (yfov = 2 atan(verticalAperture / (2 focalLength)),
  clipping range to znear/zfar); one camera: the stage's render settings' camera, else the
  first met. Depth of field (fStop, focusDistance) is reported for the job's aperture_radius
  (focalLength / (2 fStop), in metres) and focus_distance.
- Lights (radiance L = intensity x 2^exposure x color x blackbody(colorTemperature) when
  enabled, divided by the light's world-space area when normalize is on): rect, disk and sphere
  lights become emissive meshes of that radiance (emitting along -Z for rect and disk, one-sided;
  outward for a sphere); a distant light a KHR_lights_punctual directional light of illuminance
  L x solid angle of its disk (normalized: intensity x 2^exposure is the illuminance); a
  treatAsPoint sphere light a point light of intensity L x pi r^2, a spot light when its
  ShapingAPI cone is authored (_shaping: the cone's cutoff and half-intensity angle kept); a
  dome light the job's environment (its .hdr/.exr latitude-longitude texture, or a constant
  map of its colour, with intensity x 2^exposure and its turn about the up axis;
  Conversion.environment).
What cannot be carried is one warning per prim path (`warnings`), and a stage with nothing to
render is refused.

It stays one module: the conversion is one walk over the composed stage whose parts (nodes,
meshes, instances, lights, cameras, animation) share the walk's state and write into one glTF
document; the materials (usd_materials.py), the asset-path checks (usd_assets.py) and the GLB
writing (gltf_writer.py) are apart.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ...errors import SceneError
from .gltf_writer import GltfWriter
from .usd_assets import DroppedArc, check_layers, check_used_layers, packaged_copy, read_inside
from .usd_materials import MaterialConverter, _set_emission

# The intrinsic shapes tessellated (gprim), by UsdGeom class name.
SHAPES = ("Cube", "Sphere", "Cylinder", "Cylinder_1", "Cone", "Capsule", "Plane")
MAX_NODES = 2_000_000
MAX_ANIMATION_SAMPLES = 100_000
MAX_MORPH_VALUES = 8_000_000  # points over every sample of a deforming mesh (96 MB of targets)
MAX_TOPOLOGIES = 64  # meshes of one prim whose topology changes over time (thinned beyond)


@dataclass
class Conversion:
    glb: bytes
    warnings: list[str] = field(default_factory=list)
    camera: dict[str, float] = field(default_factory=dict)  # aperture_radius, focus_distance
    meters_per_unit: float = 1.0
    up_axis: str = "Y"
    # A dome light as the job's environment: data (.hdr/.exr bytes), filename, intensity,
    # rotation_deg, prim.
    environment: dict[str, Any] | None = None


def light_radiance(prim, time, area: float | None) -> np.ndarray:
    """A UsdLux light's radiance in the rendering colour space (nits): intensity x 2^exposure x
    color (x the blackbody colour when enableColorTemperature), divided by `area` when the
    light's normalize is on and an area is given."""
    from pxr import UsdLux

    api = UsdLux.LightAPI(prim)
    intensity = float(api.GetIntensityAttr().Get(time))
    exposure = float(api.GetExposureAttr().Get(time))
    color = np.array(api.GetColorAttr().Get(time), dtype=np.float64)
    if api.GetEnableColorTemperatureAttr().Get(time):
        color = color * np.array(
            UsdLux.BlackbodyTemperatureAsRgb(float(api.GetColorTemperatureAttr().Get(time)))
        )
    radiance = intensity * 2.0**exposure * color
    if area is not None and api.GetNormalizeAttr().Get(time):
        radiance = radiance / area
    return radiance


def _gltf_matrix(matrix, mpu: float) -> list[float] | None:
    """A USD (row-vector) Gf.Matrix4d as glTF's column-major matrix with its translation in
    metres; None for the identity. USD's p' = p M is glTF's p' = M^T p, and the column-major
    list of M^T is M's rows in order."""
    rows = np.array(matrix, dtype=np.float64).reshape(4, 4)
    rows[3, :3] *= mpu
    if np.allclose(rows, np.eye(4), atol=1e-12):
        return None
    return [float(v) for v in rows.reshape(-1)]


def _decompose(matrix, mpu: float):
    """(translation in metres, rotation quaternion xyzw, scale, sheared) of a USD row-vector
    matrix: the column-vector A = M^T split as A = T R S (a mirror kept as a negative x scale)."""
    a = np.array(matrix, dtype=np.float64).reshape(4, 4).T
    translation = a[:3, 3] * mpu
    basis = a[:3, :3]
    scale = np.linalg.norm(basis, axis=0)
    rot = basis / np.maximum(scale, 1e-30)
    if np.linalg.det(rot) < 0:
        scale[0] = -scale[0]
        rot[:, 0] = -rot[:, 0]
    sheared = not np.allclose(rot.T @ rot, np.eye(3), atol=1e-5)
    return translation, _quaternion(rot), scale, sheared


def _set_trs(node: dict[str, Any], matrix, mpu: float) -> None:
    translation, rotation, scale, _ = _decompose(matrix, mpu)
    node["translation"] = [float(v) for v in translation]
    node["rotation"] = [float(v) for v in rotation]
    node["scale"] = [float(v) for v in scale]


def _quaternion(r: np.ndarray) -> np.ndarray:
    """The unit quaternion (x, y, z, w) of a rotation matrix (Shepperd's method)."""
    trace = r[0, 0] + r[1, 1] + r[2, 2]
    if trace > 0:
        s = 2.0 * math.sqrt(trace + 1.0)
        q = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, s / 4]
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q = [s / 4, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s]
    elif r[1, 1] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        q = [(r[0, 1] + r[1, 0]) / s, s / 4, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        q = [(r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, s / 4, (r[1, 0] - r[0, 1]) / s]
    q = np.array(q)
    return q / np.linalg.norm(q)


def _fan(counts: np.ndarray) -> np.ndarray:
    """(triangles, 3) corner indices of faces with `counts` corners, each fanned from its first."""
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    tris_per = np.maximum(counts - 2, 0)
    face = np.repeat(np.arange(len(counts)), tris_per)
    first_tri = np.concatenate([[0], np.cumsum(tris_per)[:-1]])
    k = np.arange(int(tris_per.sum())) - np.repeat(first_tri, tris_per) + 1
    s = starts[face]
    return np.stack([s, s + k, s + k + 1], axis=1)


def _point_normals(points, counts, indices, left: bool) -> np.ndarray:
    """Each point's unit normal: the sum of the area-weighted normals of the faces it is a
    corner of (a face's normal the sum of its fan triangles' cross products, counted once
    per corner), outward for the mesh's orientation."""
    fan = _fan(counts)
    corners = points[indices[fan]]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    face_of_corner = np.repeat(np.arange(len(counts)), counts)
    faces = np.zeros((len(counts), 3))
    np.add.at(faces, face_of_corner[fan[:, 0]], cross)
    if left:
        faces = -faces
    sums = np.zeros_like(points)
    np.add.at(sums, indices, faces[face_of_corner])
    length = np.linalg.norm(sums, axis=1, keepdims=True)
    return np.where(length > 0, sums / np.maximum(length, 1e-30), [0.0, 0.0, 1.0])


class _StageConverter:
    def __init__(self, stage, root: Path, work: Path):
        from pxr import Usd, UsdGeom, UsdSkel

        self.stage = stage
        self.root = root
        self.mpu = float(UsdGeom.GetStageMetersPerUnit(stage))
        self.up = str(UsdGeom.GetStageUpAxis(stage))
        if stage.HasAuthoredTimeCodeRange():
            self.time = Usd.TimeCode(stage.GetStartTimeCode())
        else:
            self.time = Usd.TimeCode.EarliestTime()
        self.writer = GltfWriter("renderfarm usd_convert (usd-core)")
        self.warnings: dict[str, list[str]] = {}
        self.work = work  # scratch files (a re-encoded dome texture)
        self.materials = MaterialConverter(self.writer, root, work, self.warn)
        self.meshes: dict[tuple, int] = {}
        self.plain_materials: dict[tuple, int] = {}
        self.camera_prim = None
        self.camera: dict[str, float] = {}
        self.node_count = 0
        self.renderables = 0
        self.environment: dict[str, Any] | None = None
        self.time_codes_per_second = float(stage.GetTimeCodesPerSecond()) or 24.0
        self.animation: dict[str, Any] = {"name": "usd", "samplers": []}
        self.channels: list[dict[str, Any]] = []
        self.time_accessors: dict[bytes, int] = {}  # sample times -> their accessor
        self.mesh_morphs: dict[str, tuple[np.ndarray, np.ndarray]] = {}  # (times, weights)
        self.skel_cache = UsdSkel.Cache()
        self.joint_nodes: dict[str, list[int]] = {}  # skeleton path -> joint nodes, its order
        self.mesh_skins: dict[str, tuple[str, np.ndarray]] = {}  # mesh -> (skeleton, IBMs)
        self.pending_skins: list[tuple[dict, str, np.ndarray, str]] = []
        self.materialx_prims: list[tuple[str, str]] = []  # (prim, .mtlx) of dropped arcs

    def dropped_materialx(self, arcs: list[DroppedArc]) -> None:
        """Warn once per MaterialX arc check_layers dropped, and remember where, so that a
        binding to one of the document's materials says why it finds none."""
        for arc in arcs:
            variant = f" (in variant {arc.variant})" if arc.variant else ""
            self.warn(arc.where, f"the {arc.kind} to the MaterialX document {arc.asset}{variant} "
                      "is dropped (MaterialX is not converted): prims bound to its materials "
                      "get the default material")  # fmt: skip
            if arc.kind != "sublayer":
                self.materialx_prims.append((arc.where, arc.asset))

    def warn(self, path: str, text: str) -> None:
        texts = self.warnings.setdefault(path, [])
        if text not in texts:
            texts.append(text)

    # ------------------------------------------------------------------ traversal
    def convert(self) -> Conversion:
        from pxr import Usd

        self.camera_prim = self._chosen_camera()
        roots = []
        for prim in self.stage.GetPseudoRoot().GetFilteredChildren(Usd.PrimDefaultPredicate):
            node = self.walk(prim)
            if node is not None:
                roots.append(node)
        if self.renderables == 0:
            raise SceneError(
                "the stage has no mesh, gprim or light that converts to glTF: nothing to render"
                + self._warning_summary()
            )
        top: dict[str, Any] = {"name": "usd stage", "children": roots}
        if self.up == "Z":
            top["rotation"] = [-math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5)]  # -90 deg about X
        scene_root = self.writer.add("nodes", top)
        self.resolve_skins()
        if self.channels:
            self.animation["channels"] = self.channels
            self.writer.doc["animations"] = [self.animation]
        self.writer.doc["scenes"] = [{"nodes": [scene_root]}]
        self.writer.doc["scene"] = 0
        warnings = [f"{p}: {t}" for p, texts in self.warnings.items() for t in texts]
        return Conversion(
            glb=self.writer.glb(),
            warnings=warnings,
            camera=self.camera,
            meters_per_unit=self.mpu,
            up_axis=self.up,
            environment=self.environment,
        )

    def _warning_summary(self) -> str:
        items = [f"{p}: {t}" for p, texts in self.warnings.items() for t in texts][:5]
        return (" (" + "; ".join(items) + ")") if items else ""

    def _chosen_camera(self):
        from pxr import Usd, UsdGeom, UsdRender

        settings = UsdRender.Settings.GetStageRenderSettings(self.stage)
        if settings:
            targets = settings.GetCameraRel().GetForwardedTargets()
            if targets:
                prim = self.stage.GetPrimAtPath(targets[0])
                if prim and prim.IsA(UsdGeom.Camera):
                    return prim
        for prim in Usd.PrimRange(self.stage.GetPseudoRoot(), Usd.PrimDefaultPredicate):
            if prim.IsA(UsdGeom.Camera):
                return prim
        return None

    def _visible(self, prim) -> bool:
        from pxr import UsdGeom

        if not prim.IsA(UsdGeom.Imageable):
            return True
        imageable = UsdGeom.Imageable(prim)
        if imageable.GetVisibilityAttr().Get(self.time) == UsdGeom.Tokens.invisible:
            return False
        return imageable.GetPurposeAttr().Get(self.time) not in (
            UsdGeom.Tokens.guide,
            UsdGeom.Tokens.proxy,
        )

    def walk(self, prim, *, own_xform: bool = True) -> int | None:
        """The glTF node of a prim and its subtree (None when nothing under it renders)."""
        from pxr import Usd, UsdGeom, UsdLux, UsdSkel

        if not self._visible(prim):
            return None
        self.node_count += 1
        if self.node_count > MAX_NODES:
            raise SceneError(f"the stage expands to more than {MAX_NODES} nodes")
        path = str(prim.GetPath())
        node: dict[str, Any] = {"name": prim.GetName()}
        if own_xform and prim.IsA(UsdGeom.Xformable):
            xformable = UsdGeom.Xformable(prim)
            if xformable.GetResetXformStack():
                self.warn(path, "resetXformStack is ignored (the parent transform still applies)")
            animation = None
            if xformable.TransformMightBeTimeVarying():
                animation = self.transform_animation(xformable, node)
            if animation is None:
                matrix = _gltf_matrix(xformable.GetLocalTransformation(self.time), self.mpu)
                if matrix is not None:
                    node["matrix"] = matrix
        else:
            animation = None
        if prim.IsA(UsdSkel.Root):
            self.skel_cache.Populate(UsdSkel.Root(prim), Usd.PrimDefaultPredicate)
        children: list[int] = []
        walk_children = True
        spans = self.topology_spans(prim) if prim.IsA(UsdGeom.Mesh) else None
        if spans is not None:
            children += self.topology_meshes(prim, spans)
        elif prim.IsA(UsdGeom.Mesh):
            mesh = self.mesh(prim)
            if mesh is not None:
                node["mesh"] = mesh
                if path in self.mesh_morphs:
                    animation = (animation or []) + [self.morph_channel(*self.mesh_morphs[path])]
                if path in self.mesh_skins:
                    self.pending_skins.append((node, *self.mesh_skins[path], path))
        elif any(prim.IsA(getattr(UsdGeom, kind, UsdGeom.Cube)) for kind in SHAPES):
            node["mesh"] = self.gprim(prim)
        elif prim.IsA(UsdGeom.Camera):
            if self.camera_prim is not None and prim.GetPath() == self.camera_prim.GetPath():
                node["camera"] = self.camera_of(prim)
            else:
                self.warn(path, f"a second camera; the farm renders {self.camera_prim.GetPath()}")
        elif prim.IsA(UsdSkel.Skeleton):
            children += self.skeleton_joints(prim)
        elif prim.IsA(UsdGeom.PointInstancer):
            children = self.point_instancer(prim)
            walk_children = False
        elif prim.HasAPI(UsdLux.LightAPI) and not prim.IsA(UsdGeom.Gprim):
            self.light(prim, node)
        elif prim.IsA(UsdGeom.Gprim):
            self.warn(path, f"{prim.GetTypeName()} prims are not converted")
        elif prim.GetTypeName() in ("Volume", "OpenVDBAsset", "Field3DAsset"):
            self.warn(path, "volumes are not converted")
        if prim.HasAPI(UsdLux.LightAPI) and prim.IsA(UsdGeom.Gprim):
            self.warn(path, "mesh lights (MeshLightAPI) are not converted: the mesh renders unlit")
        if walk_children:
            source = prim.GetPrototype() if prim.IsInstance() else prim
            for child in source.GetFilteredChildren(Usd.PrimDefaultPredicate):
                index = self.walk(child)
                if index is not None:
                    children.append(index)
        if children:
            node["children"] = children
        if not any(k in node for k in ("mesh", "camera", "children", "extensions")):
            return None
        if animation and "matrix" in node:  # glTF: an animated node has no matrix
            rows = np.array(node.pop("matrix")).reshape(4, 4)
            _set_trs(node, rows, 1.0)  # (its translation is in metres already)
        index = self.writer.add("nodes", node)
        if animation is not None:
            for channel in animation:
                channel["target"]["node"] = index
            self.channels += animation
        return index

    def transform_animation(self, xformable, node: dict[str, Any]) -> list[dict] | None:
        """glTF animation channels (their target node left to the caller) for a prim whose
        transform has time samples (trs_animation of its local transformation)."""
        return self.trs_animation(
            str(xformable.GetPath()),
            xformable.GetTimeSamples(),
            xformable.GetLocalTransformation,
            node,
        )

    def trs_animation(self, path: str, authored, matrix_at, node: dict) -> list[dict] | None:
        """Channels of the glTF animation "usd" for a local transformation `matrix_at(time)`
        with time samples at `authored`: sampled at every authored time and every whole time
        code between the first and the last (USD interpolates each xformOp's or joint's
        components, so whole frames are exact for a farm job at fps = timeCodesPerSecond),
        split into translation (metres), rotation and scale, LINEAR; glTF time = time code /
        timeCodesPerSecond. The node takes TRS at the stage's start time. None when fewer than
        two samples."""
        from pxr import Usd

        authored = sorted(set(authored))
        if len(authored) < 2:
            return None
        first, last = authored[0], authored[-1]
        whole = np.arange(math.ceil(first), math.floor(last) + 1, dtype=np.float64)
        times = np.unique(np.concatenate([np.array(authored), whole]))
        if len(times) > MAX_ANIMATION_SAMPLES:
            self.warn(path, f"more than {MAX_ANIMATION_SAMPLES} transform samples: thinned")
            times = times[:: math.ceil(len(times) / MAX_ANIMATION_SAMPLES)]
        trs = [_decompose(matrix_at(Usd.TimeCode(float(t))), self.mpu) for t in times]
        if any(sheared for *_, sheared in trs):
            self.warn(path, "a sheared transform animates without its shear")
        rotations = [r for _, r, _, _ in trs]
        for i in range(1, len(rotations)):  # the shorter arc between neighbouring keys
            if np.dot(rotations[i], rotations[i - 1]) < 0:
                rotations[i] = -rotations[i]
        _set_trs(node, matrix_at(self.time), self.mpu)
        key = times.tobytes()
        seconds = self.time_accessors.get(key)
        if seconds is None:
            seconds = self.writer.accessor(times / self.time_codes_per_second, bounds=True)
            self.time_accessors[key] = seconds
        channels = []
        for name, values in (
            ("translation", [t for t, _, _, _ in trs]),
            ("rotation", rotations),
            ("scale", [s for _, _, s, _ in trs]),
        ):
            values = np.array(values)
            if np.allclose(values, values[0], atol=1e-9):
                continue
            sampler = {"input": seconds, "output": self.writer.accessor(values)}
            samplers = self.animation["samplers"]
            samplers.append({**sampler, "interpolation": "LINEAR"})
            channels.append({"sampler": len(samplers) - 1, "target": {"path": name}})
        return channels or None

    # ------------------------------------------------------------------ skeletons
    def skeleton_joints(self, prim) -> list[int]:
        """A UsdSkel Skeleton's joints as glTF nodes under its own node (their local
        transforms, animated by its bound SkelAnimation); returns the root joints' nodes and
        remembers every joint's node in skeleton order for the skins."""
        from pxr import UsdSkel

        path = str(prim.GetPath())
        query = self.skel_cache.GetSkelQuery(UsdSkel.Skeleton(prim))
        if not query:
            self.warn(path, "a skeleton UsdSkel cannot read: its meshes stay in their bind pose")
            return []
        order = list(query.GetJointOrder())
        parents = list(query.GetTopology().GetParentIndices())
        anim = query.GetAnimQuery()
        authored = list(anim.GetJointTransformTimeSamples()) if anim else []
        nodes: list[dict[str, Any]] = []
        indices: list[int] = []
        channels_of: list[list[dict] | None] = []
        for j, joint in enumerate(order):
            node: dict[str, Any] = {"name": str(joint).rsplit("/", 1)[-1]}

            def local_at(time, j: int = j):
                return query.ComputeJointLocalTransforms(time)[j]

            channels = self.trs_animation(f"{path} joint {joint}", authored, local_at, node)
            if channels is None:
                _set_trs(node, query.ComputeJointLocalTransforms(self.time)[j], self.mpu)
            nodes.append(node)
            channels_of.append(channels)
        for node, channels in zip(nodes, channels_of, strict=True):
            index = self.writer.add("nodes", node)
            indices.append(index)
            for channel in channels or []:
                channel["target"]["node"] = index
                self.channels.append(channel)
        roots = []
        for j, parent in enumerate(parents):
            if parent < 0:
                roots.append(indices[j])
            else:
                nodes[parent].setdefault("children", []).append(indices[j])
        self.joint_nodes[path] = indices
        return roots

    def skin_attributes(self, prim, indices: np.ndarray, n_points: int) -> dict | None:
        """JOINTS_0 and WEIGHTS_0 per face corner for a mesh UsdSkel binds to a skeleton (the
        four largest influences of each point, renormalized), and the skin to give its node
        later (self.pending_skins); None when the mesh is not skinned."""
        from pxr import UsdSkel

        path = str(prim.GetPath())
        skinning = self.skel_cache.GetSkinningQuery(prim)
        if not skinning or not skinning.HasJointInfluences():
            return None
        skeleton = UsdSkel.BindingAPI(prim).GetInheritedSkeleton()
        query = self.skel_cache.GetSkelQuery(skeleton) if skeleton else None
        if not query:
            self.warn(path, "bound to no skeleton UsdSkel can read: rendered in its bind pose")
            return None
        if skinning.GetSkinningMethod() == UsdSkel.Tokens.dualQuaternion:
            self.warn(path, "dual-quaternion skinning is rendered as linear blend skinning "
                      "(glTF's only skinning): joints that twist lose volume")  # fmt: skip
        joint_ids, weights = skinning.ComputeVaryingJointInfluences(n_points, self.time)
        width = skinning.GetNumInfluencesPerComponent()
        joint_ids = np.array(joint_ids, dtype=np.int64).reshape(n_points, width)
        weights = np.array(weights, dtype=np.float64).reshape(n_points, width)
        skel_order = [str(j) for j in query.GetJointOrder()]
        local_order = skinning.GetJointOrder()
        if local_order:  # the mesh's own skel:joints order: map to the skeleton's
            remap = np.array([skel_order.index(str(j)) for j in local_order], dtype=np.int64)
            joint_ids = remap[np.clip(joint_ids, 0, len(remap) - 1)]
        if width > 4:
            self.warn(path, f"{width} joint influences per point: the 4 largest are kept")
        keep = np.argsort(-weights, axis=1)[:, :4]
        joint_ids = np.take_along_axis(joint_ids, keep, axis=1)
        weights = np.take_along_axis(weights, keep, axis=1)
        if width < 4:
            pad = 4 - width
            joint_ids = np.pad(joint_ids, ((0, 0), (0, pad)))
            weights = np.pad(weights, ((0, 0), (0, pad)))
        total = weights.sum(axis=1, keepdims=True)
        weights = np.where(total > 0, weights / np.where(total > 0, total, 1.0), 0.0)
        geom_bind = np.array(skinning.GetGeomBindTransform(self.time), dtype=np.float64)
        binds = query.GetJointWorldBindTransforms()
        if not binds or len(binds) != len(skel_order):
            self.warn(path, "its skeleton has no bind transforms: rendered in its bind pose")
            return None
        ibm = []
        for bind in binds:
            # USD row vectors: p_skel = p GB B^-1 J; glTF: G_j IBM_j p, IBM_j = (GB B^-1)^T.
            m = geom_bind.reshape(4, 4) @ np.linalg.inv(np.array(bind).reshape(4, 4))
            m[3, :3] *= self.mpu
            ibm.append(m.reshape(-1))
        return {
            "JOINTS_0": joint_ids[indices].astype(np.float64),
            "WEIGHTS_0": weights[indices],
            "skeleton": str(skeleton.GetPath()),
            "ibm": np.array(ibm),
        }

    def resolve_skins(self) -> None:
        for node, skeleton, ibm, path in self.pending_skins:
            joints = self.joint_nodes.get(skeleton)
            if not joints:
                self.warn(path, f"its skeleton {skeleton} is not rendered: no skin")
                continue
            accessor = self.writer.accessor(ibm)
            node["skin"] = self.writer.add(
                "skins", {"name": skeleton, "joints": joints, "inverseBindMatrices": accessor}
            )

    # ------------------------------------------------------------------ instancing
    def point_instancer(self, prim) -> list[int]:
        from pxr import UsdGeom

        path = str(prim.GetPath())
        instancer = UsdGeom.PointInstancer(prim)
        protos = instancer.GetPrototypesRel().GetForwardedTargets()
        indices = instancer.GetProtoIndicesAttr().Get(self.time)
        if indices is None or not protos:
            return []
        indices = np.array(indices, dtype=np.int64)
        if len(indices) and (indices.min() < 0 or indices.max() >= len(protos)):
            raise SceneError(
                f"{path}.protoIndices: an index is outside the {len(protos)} prototypes",
                f"scene:{path}.protoIndices",
            )
        xforms = instancer.ComputeInstanceTransformsAtTime(
            self.time,
            self.time,
            UsdGeom.PointInstancer.IncludeProtoXform,
            UsdGeom.PointInstancer.IgnoreMask,
        )
        if xforms is None or len(xforms) != len(indices):
            raise SceneError(
                f"{path}: positions, orientations and scales do not match protoIndices",
                f"scene:{path}.positions",
            )
        mask = instancer.ComputeMaskAtTime(self.time)
        proto_prims = [self.stage.GetPrimAtPath(p) for p in protos]
        at_time = self._instancer_samples(instancer, len(indices))
        nodes = []
        for i, (matrix, proto) in enumerate(zip(xforms, indices, strict=True)):
            if mask and not mask[i]:
                continue
            child = self.walk(proto_prims[proto], own_xform=False)
            if child is None:
                continue
            node: dict[str, Any] = {"name": f"{prim.GetName()}[{i}]", "children": [child]}
            channels = None
            if at_time:

                def matrix_at(time, i: int = i, start=matrix):
                    sample = at_time.get(time.GetValue()) if time.IsNumeric() else None
                    return start if sample is None else sample[i]

                channels = self.trs_animation(f"{path}[{i}]", list(at_time), matrix_at, node)
            if channels is None:
                for key in ("translation", "rotation", "scale"):
                    node.pop(key, None)
                gltf = _gltf_matrix(matrix, self.mpu)
                if gltf is not None:
                    node["matrix"] = gltf
            index = self.writer.add("nodes", node)
            for channel in channels or []:
                channel["target"]["node"] = index
                self.channels.append(channel)
            nodes.append(index)
        return nodes

    def _instancer_samples(self, instancer, count: int) -> dict[float, Any]:
        """The instance transforms at each time the instancer's positions, orientations or
        scales are sampled, and at every whole time code between the first and the last
        ({time code: transforms}); empty when they do not vary or the instances change."""
        from pxr import Usd, UsdGeom

        path = str(instancer.GetPath())
        attrs = [
            instancer.GetPositionsAttr(),
            instancer.GetOrientationsAttr(),
            instancer.GetOrientationsfAttr(),
            instancer.GetScalesAttr(),
        ]
        authored = sorted({t for a in attrs if a for t in a.GetTimeSamples()})
        if len(authored) < 2:
            return {}
        if instancer.GetProtoIndicesAttr().ValueMightBeTimeVarying():
            self.warn(path, "instances that change over time are converted at the first time")
            return {}
        whole = np.arange(math.ceil(authored[0]), math.floor(authored[-1]) + 1)
        times = sorted(set(authored) | {float(t) for t in whole})
        if len(times) * count > MAX_ANIMATION_SAMPLES * 10:
            self.warn(path, "too many animated instance keys: instances converted at first time")
            return {}
        samples = {}
        for t in times:
            code = Usd.TimeCode(t)
            xforms = instancer.ComputeInstanceTransformsAtTime(
                code, code, UsdGeom.PointInstancer.IncludeProtoXform,
                UsdGeom.PointInstancer.IgnoreMask,
            )  # fmt: skip
            if xforms is None or len(xforms) != count:
                self.warn(path, "the instance count changes over time: converted at first time")
                return {}
            samples[float(t)] = xforms
        return samples

    # ------------------------------------------------------------------ materials
    def _material_for(self, prim, double_sided: bool):
        from pxr import UsdShade

        # The binding for a final render: the full-purpose one, else the all-purpose one.
        binding = UsdShade.MaterialBindingAPI(prim)
        material, rel = binding.ComputeBoundMaterial(UsdShade.Tokens.full)
        if not material:
            targets = rel.GetTargets() if rel else []
            if targets:  # bound to a prim that is no material (or not on the stage)
                self._warn_unbound(str(targets[0]))
            return None
        return self.materials.convert(material, double_sided)

    def _warn_unbound(self, target: str) -> None:
        assets = [a for w, a in self.materialx_prims if target == w or target.startswith(w + "/")]
        if assets:  # under a prim whose MaterialX arcs were dropped: from one of them
            named = " or ".join(dict.fromkeys(assets))
            self.warn(target, f"a material of the dropped MaterialX document {named}: not "
                      "converted, the prims bound to it get the default material")  # fmt: skip
            return
        self.warn(target, "bound as a material but not a Material on the stage: the prims "
                  "bound to it get the default material")  # fmt: skip

    def _plain_material(
        self, color, opacity: float, double_sided: bool, vertex_colors: bool
    ) -> int:
        key = (
            tuple(round(float(c), 6) for c in color),
            round(opacity, 6),
            double_sided,
            vertex_colors,
        )
        index = self.plain_materials.get(key)
        if index is None:
            gltf: dict[str, Any] = {
                "name": "displayColor",
                "pbrMetallicRoughness": {
                    "baseColorFactor": [*(float(c) for c in color), float(opacity)],
                    "metallicFactor": 0.0,
                    "roughnessFactor": 0.5,
                },
            }
            if opacity < 1.0 or vertex_colors:
                gltf["alphaMode"] = (
                    "BLEND" if opacity < 1.0 or vertex_colors == "alpha" else "OPAQUE"
                )
            if double_sided:
                gltf["doubleSided"] = True
            index = self.writer.add("materials", gltf)
            self.plain_materials[key] = index
        return index

    # ------------------------------------------------------------------ meshes
    def _primvar(self, prim, name: str):
        from pxr import UsdGeom

        primvar = UsdGeom.PrimvarsAPI(prim).GetPrimvar(name)
        if not primvar or not primvar.HasAuthoredValue():
            return None, None
        values = primvar.ComputeFlattened(self.time)
        if values is None:
            return None, None
        return np.array(values, dtype=np.float64), str(primvar.GetInterpolation())

    def _per_corner(self, values, interp, counts, indices, n_points, where, width):
        """Per-corner values (corners, width) of a primvar with the given interpolation."""
        values = values.reshape(len(values), -1) if values.ndim > 1 else values.reshape(-1, 1)
        corners = len(indices)
        if interp == "constant" or len(values) == 1 and interp != "faceVarying":
            return np.repeat(values[:1], corners, axis=0)
        if interp == "uniform":
            expected = len(counts)
            if len(values) < expected:
                raise SceneError(
                    f"{where}: {len(values)} uniform values for {expected} faces", f"scene:{where}"
                )
            return np.repeat(values[:expected], counts, axis=0)
        if interp in ("vertex", "varying"):
            if len(values) < n_points:
                raise SceneError(
                    f"{where}: {len(values)} values for {n_points} points", f"scene:{where}"
                )
            return values[indices]
        if interp == "faceVarying":
            if len(values) < corners:
                raise SceneError(
                    f"{where}: {len(values)} face-varying values for {corners} face corners",
                    f"scene:{where}",
                )
            return values[:corners]
        raise SceneError(f"{where}: unknown interpolation {interp!r}", f"scene:{where}")

    def mesh(self, prim, at: float | None = None) -> int | None:
        """The glTF mesh of a UsdGeom.Mesh at the stage's start time (deforming points as
        morph targets), or with `at`, its topology and points at that time code, unmoving (one
        of the meshes of a topology that changes: topology_meshes)."""
        from pxr import Usd

        key = ("mesh", str(prim.GetPath())) if at is None else ("mesh", str(prim.GetPath()), at)
        if key in self.meshes:
            return self.meshes[key]
        if at is None:
            return self._mesh(prim, key, fixed=False)
        start, self.time = self.time, Usd.TimeCode(at)
        try:
            return self._mesh(prim, key, fixed=True)
        finally:
            self.time = start

    def _mesh(self, prim, key: tuple, fixed: bool) -> int | None:
        from pxr import UsdGeom, UsdShade

        path = str(prim.GetPath())
        mesh = UsdGeom.Mesh(prim)
        t = self.time
        points = mesh.GetPointsAttr().Get(t)
        counts = mesh.GetFaceVertexCountsAttr().Get(t)
        indices = mesh.GetFaceVertexIndicesAttr().Get(t)
        if points is None or counts is None or indices is None or len(points) == 0:
            self.warn(path, "a mesh without points or faces")
            return None
        points = np.array(points, dtype=np.float64).reshape(-1, 3) * self.mpu
        counts = np.array(counts, dtype=np.int64)
        indices = np.array(indices, dtype=np.int64)
        if not np.all(np.isfinite(points)):
            raise SceneError(f"{path}.points: a point is not finite", f"scene:{path}.points")
        if counts.sum() != len(indices) or (counts < 0).any():
            raise SceneError(
                f"{path}.faceVertexCounts: the counts add up to {int(counts.sum())}, but "
                f"faceVertexIndices has {len(indices)} entries",
                f"scene:{path}.faceVertexCounts",
            )
        if len(indices) and (indices.min() < 0 or indices.max() >= len(points)):
            raise SceneError(
                f"{path}.faceVertexIndices: an index is outside the {len(points)} points",
                f"scene:{path}.faceVertexIndices",
            )
        scheme = mesh.GetSubdivisionSchemeAttr().Get(t)
        if scheme and scheme != "none":
            self.warn(path, f"subdivision ({scheme}) is not applied: the control cage is "
                      "rendered, smooth-shaded")  # fmt: skip
        if (counts < 3).any():
            self.warn(path, "faces with fewer than 3 corners are skipped")
        face_keep = counts >= 3
        holes = mesh.GetHoleIndicesAttr().Get(t)
        if holes is not None and len(holes):
            face_keep[np.array(holes, dtype=np.int64).clip(0, len(counts) - 1)] = False
            self.warn(path, "holes (holeIndices) are left out")
        left = mesh.GetOrientationAttr().Get(t) == UsdGeom.Tokens.leftHanded
        double_sided = bool(mesh.GetDoubleSidedAttr().Get(t))

        # Per-corner attributes: positions, normals, colours, texture coordinates.
        attributes: dict[str, np.ndarray] = {"POSITION": points[indices]}
        normals, interp = self._primvar(prim, "normals")
        if normals is None:
            raw = mesh.GetNormalsAttr().Get(t)
            if raw is not None and len(raw):
                normals, interp = (
                    np.array(raw, dtype=np.float64),
                    str(mesh.GetNormalsInterpolation()),
                )
        if normals is not None:
            n = self._per_corner(
                normals, interp, counts, indices, len(points), f"{path}.normals", 3
            )
            length = np.linalg.norm(n, axis=1, keepdims=True)
            attributes["NORMAL"] = np.where(
                length > 0, n / np.maximum(length, 1e-30), [0.0, 0.0, 1.0]
            )
        elif scheme and scheme != "none":
            # A subdivision surface is smooth (USD computes its normals from the limit
            # surface): its cage is shaded with each point's area-weighted face normals, as
            # Blender's importer and Storm shade an unsubdivided cage, not flat as glTF would.
            attributes["NORMAL"] = _point_normals(points, counts, indices, left)[indices]
        morph = None if fixed else self.morph_samples(mesh, len(points))
        weights = None  # (times, weights per time) of the morph targets
        if morph is not None:
            skinning = self.skel_cache.GetSkinningQuery(prim)
            if skinning and skinning.HasBlendShapes():
                self.warn(path, "blend shapes on points that have time samples are not "
                          "converted: the points' samples are")  # fmt: skip
            times, frames = morph
            displacements = [frame - points for frame in frames]
            weights = (times, np.eye(len(times)))
            normal_frames = self.morph_normals(prim, mesh, times, counts, indices, len(points))
            if normal_frames is not None and "NORMAL" in attributes:
                # Per corner, so part of the weld: corners apart at any time stay apart.
                for k, frame in enumerate(normal_frames):
                    attributes[f"_NORMAL_TARGET{k:06d}"] = frame - attributes["NORMAL"]
        else:
            if not fixed and self._normals_vary(prim, mesh):
                self.warn(path, "normals that change over time on points that do not: the "
                          "first time's normals are kept")  # fmt: skip
            shapes = self.blend_shapes(prim, len(points))
            displacements, weights = shapes if shapes is not None else (None, None)
        if displacements is not None:  # welded apart by point: each vertex follows its point
            attributes["_POINT"] = indices.astype(np.float64)
        skin = self.skin_attributes(prim, indices, len(points))
        if skin is not None:
            attributes["JOINTS_0"] = skin["JOINTS_0"]
            attributes["WEIGHTS_0"] = skin["WEIGHTS_0"]
            self.mesh_skins[path] = (skin["skeleton"], skin["ibm"])

        # Material per face: GeomSubsets of the materialBind family, the rest the mesh's.
        face_material: dict[int, Any] = {}
        binding = UsdShade.MaterialBindingAPI(prim)
        groups: list[tuple[np.ndarray, Any]] = []
        assigned = np.zeros(len(counts), dtype=bool)
        for subset in binding.GetMaterialBindSubsets():
            faces = subset.GetIndicesAttr().Get(t)
            if faces is None:
                continue
            faces = np.array(faces, dtype=np.int64)
            if len(faces) and (faces.min() < 0 or faces.max() >= len(counts)):
                sp = str(subset.GetPath())
                raise SceneError(
                    f"{sp}.indices: a face index is outside the mesh's {len(counts)} faces",
                    f"scene:{sp}.indices",
                )
            faces = faces[~assigned[faces]]
            assigned[faces] = True
            groups.append((faces, self._material_for(subset.GetPrim(), double_sided)))
        rest = np.flatnonzero(~assigned)
        if len(rest):
            groups.append((rest, self._material_for(prim, double_sided)))
        del face_material

        display, display_interp = self._primvar(prim, "displayColor")
        opacity, opacity_interp = self._primvar(prim, "displayOpacity")
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        primitives = []
        for faces, material in groups:
            faces = faces[face_keep[faces]]
            if not len(faces):
                continue
            sub_counts = counts[faces]
            # The corners of the chosen faces in order: each face's start plus 0..count-1.
            first = np.concatenate([[0], np.cumsum(sub_counts)[:-1]])
            within = np.arange(int(sub_counts.sum())) - np.repeat(first, sub_counts)
            corner_ids = np.repeat(starts[faces], sub_counts) + within
            tris = _fan(sub_counts)
            if left:
                tris = tris[:, [0, 2, 1]]
            attrs = {k: v[corner_ids] for k, v in attributes.items()}
            if material is not None:
                for i, name in enumerate(material.uv_sets):
                    uv, uv_interp = self._primvar(prim, name)
                    if uv is None:
                        self.warn(
                            path, f"the material reads primvar {name!r}, which the mesh lacks"
                        )
                        uv_corner = np.zeros((len(indices), 2))
                    else:
                        uv_corner = self._per_corner(
                            uv,
                            uv_interp,
                            counts,
                            indices,
                            len(points),
                            f"{path}.primvars:{name}",
                            2,
                        )[:, :2]
                    uv_corner = uv_corner[corner_ids]
                    attrs[f"TEXCOORD_{i}"] = np.stack(
                        [uv_corner[:, 0], 1.0 - uv_corner[:, 1]], axis=1
                    )
                if material.color_primvar is not None:
                    attrs["COLOR_0"] = self._primvar_colors(
                        prim, material, counts, indices, len(points)
                    )[corner_ids]
                material_index = material.index
            else:
                material_index, colors = self._display_material(
                    path,
                    display,
                    display_interp,
                    opacity,
                    opacity_interp,
                    counts,
                    indices,
                    len(points),
                    double_sided,
                )
                if colors is not None:
                    attrs["COLOR_0"] = colors[corner_ids]
            primitives.append(self._primitive(attrs, tris, material_index, displacements))
        if not primitives:
            self.warn(path, "no faces to render")
            return None
        gltf_mesh: dict[str, Any] = {"name": path, "primitives": primitives}
        if weights is not None:
            times, values = weights
            at = int(np.argmin(np.abs(times - float(self.time.GetValue()))))
            gltf_mesh["weights"] = [float(w) for w in values[at]]
            if len(times) >= 2:
                self.mesh_morphs[path] = (times, values)
        index = self.writer.add("meshes", gltf_mesh)
        self.meshes[key] = index
        self.renderables += 1
        return index

    def topology_spans(self, prim) -> list[float] | None:
        """The time codes at which a mesh's topology (its point count, faceVertexCounts or
        faceVertexIndices) changes, the first of its samples included: each starts a span
        that lasts until the next (USD holds an array whose size or integers change until its
        next sample); None when the topology is one over time."""
        import hashlib

        from pxr import UsdGeom

        mesh = UsdGeom.Mesh(prim)
        attrs = (mesh.GetPointsAttr(), mesh.GetFaceVertexCountsAttr(),
                 mesh.GetFaceVertexIndicesAttr())  # fmt: skip
        if not attrs[1].ValueMightBeTimeVarying() and not attrs[2].ValueMightBeTimeVarying():
            if not attrs[0].ValueMightBeTimeVarying():
                return None
        times = sorted({t for a in attrs for t in a.GetTimeSamples()})
        if len(times) < 2:
            return None
        starts: list[float] = []
        last = None
        for t in times:
            points, counts, indices = (a.Get(t) for a in attrs)
            digest = hashlib.sha256()
            digest.update(str(len(points) if points is not None else -1).encode())
            for values in (counts, indices):
                digest.update(b"|" + np.asarray(values if values is not None else [],
                                                 dtype=np.int64).tobytes())  # fmt: skip
            if digest.digest() != last:
                starts.append(float(t))
                last = digest.digest()
        return starts if len(starts) >= 2 else None

    def topology_meshes(self, prim, starts: list[float]) -> list[int]:
        """A mesh whose topology changes over time as one glTF mesh per span of one topology
        (at most MAX_TOPOLOGIES, thinned evenly beyond: each kept span lasts until the next
        kept one), each converted at its span's first time code and unmoving, on a child node
        of its own that KHR_node_visibility shows during its span alone: a STEP channel of
        KHR_animation_pointer per node over the spans' start times (glTF seconds = time code /
        timeCodesPerSecond), visible at its own start, hidden at the others'. Before the first
        sample the first span shows, after the last the last (USD holds its first and last
        samples); a still shows the span at the stage's start time."""
        path = str(prim.GetPath())
        moving = [t for t in prim.GetAttribute("points").GetTimeSamples() if t not in starts]
        if any(t > starts[0] for t in moving):
            self.warn(path, "points that move while the topology holds are not animated: each "
                      "topology is converted at the first time it holds")  # fmt: skip
        if len(starts) > MAX_TOPOLOGIES:
            self.warn(path, f"{len(starts)} topologies over time: thinned to {MAX_TOPOLOGIES}, "
                      "each shown until the next kept one")  # fmt: skip
            keep = np.linspace(0, len(starts) - 1, MAX_TOPOLOGIES).round().astype(int)
            starts = [starts[int(k)] for k in np.unique(keep)]
        start = float(self.time.GetValue()) if self.time.IsNumeric() else starts[0]
        shown = max([k for k, t in enumerate(starts) if t <= start] or [0])
        times = np.array(starts, dtype=np.float64)
        key = times.tobytes()
        seconds = self.time_accessors.get(key)
        if seconds is None:
            seconds = self.writer.accessor(times / self.time_codes_per_second, bounds=True)
            self.time_accessors[key] = seconds
        nodes = []
        for k, t in enumerate(starts):
            mesh = self.mesh(prim, at=t)
            if mesh is None:
                continue
            node: dict[str, Any] = {
                "name": f"{prim.GetName()}@{t:g}",
                "mesh": mesh,
                "extensions": {"KHR_node_visibility": {"visible": k == shown}},
            }
            index = self.writer.add("nodes", node)
            if path in self.mesh_skins:
                self.pending_skins.append((node, *self.mesh_skins[path], path))
            samplers = self.animation["samplers"]
            output = self.writer.bool_accessor(np.arange(len(starts)) == k)
            samplers.append({"input": seconds, "output": output, "interpolation": "STEP"})
            pointer = f"/nodes/{index}/extensions/KHR_node_visibility/visible"
            self.channels.append({
                "sampler": len(samplers) - 1,
                "target": {"path": "pointer",
                           "extensions": {"KHR_animation_pointer": {"pointer": pointer}}},
            })  # fmt: skip
            nodes.append(index)
        if nodes:
            for name in ("KHR_node_visibility", "KHR_animation_pointer"):
                self.writer.use_extension(name)
                required = self.writer.doc.setdefault("extensionsRequired", [])
                if name not in required:
                    required.append(name)
        return nodes

    def morph_samples(self, mesh, n_points: int):
        """(time codes, the points at each in metres) of a mesh whose points have time samples
        over a fixed topology, sampled at every authored time and every whole time code
        between, at most MAX_MORPH_VALUES point values in all; None when they do not vary."""
        path = str(mesh.GetPath())
        attr = mesh.GetPointsAttr()
        authored = sorted(set(attr.GetTimeSamples()))
        if len(authored) < 2:
            return None
        for topology in (mesh.GetFaceVertexCountsAttr(), mesh.GetFaceVertexIndicesAttr()):
            if topology.ValueMightBeTimeVarying():
                self.warn(path, "a topology that changes over time: converted at the first time")
                return None
        whole = np.arange(math.ceil(authored[0]), math.floor(authored[-1]) + 1)
        times = np.unique(np.concatenate([np.array(authored), whole.astype(np.float64)]))
        if len(times) * n_points > MAX_MORPH_VALUES:
            keep = max(2, MAX_MORPH_VALUES // max(n_points, 1))
            self.warn(path, f"deforming points thinned to {keep} samples (a memory limit)")
            times = times[np.linspace(0, len(times) - 1, keep).round().astype(int)]
        frames = []
        for t in times:
            points = attr.Get(float(t))
            if points is None or len(points) != n_points:
                self.warn(path, "the point count changes over time: converted at the first time")
                return None
            frames.append(np.array(points, dtype=np.float64).reshape(-1, 3) * self.mpu)
        return times, frames

    def _normals_source(self, prim, mesh):
        """(the attribute holding the mesh's normals, its interpolation): primvars:normals
        before normals, as _primvar and mesh() read them; (None, None) without normals."""
        from pxr import UsdGeom

        primvar = UsdGeom.PrimvarsAPI(prim).GetPrimvar("normals")
        if primvar and primvar.HasAuthoredValue():
            return primvar, str(primvar.GetInterpolation())
        attr = mesh.GetNormalsAttr()
        if attr and attr.HasAuthoredValue():
            return attr, str(mesh.GetNormalsInterpolation())
        return None, None

    def _normals_vary(self, prim, mesh) -> bool:
        source, _ = self._normals_source(prim, mesh)
        attr = source.GetAttr() if hasattr(source, "GetAttr") else source
        return attr is not None and len(attr.GetTimeSamples()) >= 2

    def morph_normals(self, prim, mesh, times, counts, indices, n_points):
        """The unit normal of each face corner at each time of a deforming mesh whose normals
        have time samples too (a NORMAL morph target per time, so the shading follows the
        deformation as USD's normals do), or None when its normals do not change."""
        from pxr import UsdGeom

        path = str(prim.GetPath())
        if not self._normals_vary(prim, mesh):
            return None
        source, interp = self._normals_source(prim, mesh)
        frames = []
        for t in times:
            if isinstance(source, UsdGeom.Primvar):
                values = source.ComputeFlattened(float(t))
            else:
                values = source.Get(float(t))
            if values is None or not len(values):
                self.warn(path, "normals missing at a time: the first time's are kept")
                return None
            try:
                n = self._per_corner(np.array(values, dtype=np.float64), interp, counts,
                                     indices, n_points, f"{path}.normals", 3)  # fmt: skip
            except SceneError:
                self.warn(path, "normals whose count changes over time: the first time's are kept")
                return None
            length = np.linalg.norm(n, axis=1, keepdims=True)
            frames.append(np.where(length > 0, n / np.maximum(length, 1e-30), [0.0, 0.0, 1.0]))
        return frames

    def blend_shapes(self, prim, n_points: int):
        """UsdSkel blend shapes of a mesh as morph targets: (per-point offsets in metres for
        each of the mesh's skel:blendShapes, (time codes, the weights at each)), the weights
        of its skeleton's SkelAnimation remapped to the mesh's order (at every authored time
        and every whole time code between; one time, the stage's start, when they are not
        animated); None without blend shapes. In-between shapes and normal offsets are warned
        (the shape goes linearly to its full offsets; the normals stay)."""
        from pxr import UsdSkel

        path = str(prim.GetPath())
        skinning = self.skel_cache.GetSkinningQuery(prim)
        if not skinning or not skinning.HasBlendShapes():
            return None
        binding = UsdSkel.BindingAPI(prim)
        names = list(binding.GetBlendShapesAttr().Get() or [])
        targets = binding.GetBlendShapeTargetsRel().GetForwardedTargets()
        if not names or len(names) != len(targets):
            self.warn(path, "skel:blendShapes and skel:blendShapeTargets differ in length: "
                      "blend shapes are not converted")  # fmt: skip
            return None
        offsets = []
        for target in targets:
            shape = UsdSkel.BlendShape(self.stage.GetPrimAtPath(target))
            full = np.zeros((n_points, 3))
            if not shape:
                self.warn(path, f"blend shape target {target} is not a BlendShape: left at rest")
                offsets.append(full)
                continue
            where = str(target)
            values = np.array(shape.GetOffsetsAttr().Get() or [], dtype=np.float64).reshape(-1, 3)
            points = shape.GetPointIndicesAttr().Get()
            if points is not None and len(points):
                points = np.array(points, dtype=np.int64)
                if len(points) != len(values) or points.min() < 0 or points.max() >= n_points:
                    self.warn(where, "pointIndices do not match offsets or the mesh: left at rest")
                else:
                    full[points] = values
            elif len(values) == n_points:
                full = values.copy()
            else:
                self.warn(where, f"{len(values)} offsets for {n_points} points: left at rest")
            if shape.GetInbetweens():
                self.warn(where, "in-between shapes are not converted: the shape goes "
                          "linearly to its full offsets")  # fmt: skip
            normal_offsets = shape.GetNormalOffsetsAttr()
            if normal_offsets and normal_offsets.HasAuthoredValue():
                self.warn(where, "normalOffsets are not converted: the normals stay at rest")
            offsets.append(full * self.mpu)
        skeleton = binding.GetInheritedSkeleton()
        query = self.skel_cache.GetSkelQuery(skeleton) if skeleton else None
        anim = query.GetAnimQuery() if query else None
        start = float(self.time.GetValue())
        if not anim or not anim.GetBlendShapeOrder():
            return offsets, (np.array([start]), np.zeros((1, len(offsets))))
        mapper = skinning.GetBlendShapeMapper()

        def weights_at(t: float) -> np.ndarray:
            source = anim.ComputeBlendShapeWeights(t)
            values = mapper.Remap(source) if mapper and not mapper.IsIdentity() else source
            values = np.array(values if values is not None else [], dtype=np.float64)
            return np.resize(values, len(offsets)) if len(values) else np.zeros(len(offsets))

        authored = sorted(set(anim.GetBlendShapeWeightTimeSamples()))
        if len(authored) < 2:
            return offsets, (np.array([start]), weights_at(start)[None, :])
        whole = np.arange(math.ceil(authored[0]), math.floor(authored[-1]) + 1)
        times = np.unique(np.concatenate([np.array(authored), whole.astype(np.float64)]))
        if len(times) > MAX_ANIMATION_SAMPLES:
            self.warn(path, f"more than {MAX_ANIMATION_SAMPLES} blend shape samples: thinned")
            times = times[:: math.ceil(len(times) / MAX_ANIMATION_SAMPLES)]
        return offsets, (times, np.stack([weights_at(float(t)) for t in times]))

    def morph_channel(self, times: np.ndarray, values: np.ndarray) -> dict[str, Any]:
        """A weights channel (its node left to the caller) of the morph weights `values[k]` at
        time code `times[k]`, LINEAR. For deforming points the identity: target k alone at
        time k, so that LINEAR between neighbours blends two samples' points linearly, as USD
        interpolates points; for blend shapes the SkelAnimation's weights, which USD
        interpolates linearly too."""
        key = times.tobytes()
        seconds = self.time_accessors.get(key)
        if seconds is None:
            seconds = self.writer.accessor(times / self.time_codes_per_second, bounds=True)
            self.time_accessors[key] = seconds
        output = self.writer.accessor(np.asarray(values, dtype=np.float64).reshape(-1))
        samplers = self.animation["samplers"]
        samplers.append({"input": seconds, "output": output, "interpolation": "LINEAR"})
        return {"sampler": len(samplers) - 1, "target": {"path": "weights"}}

    def _primvar_colors(self, prim, material, counts, indices, n_points) -> np.ndarray:
        """RGBA per face corner of the primvar a material's diffuseColor reads (its reader's
        fallback where the prim lacks it), for COLOR_0."""
        name = material.color_primvar
        values, interp = self._primvar(prim, name) if name else (None, None)
        if values is None:
            values, interp = np.array([material.color_fallback], dtype=np.float64), "constant"
        rgb = self._per_corner(values, interp, counts, indices, n_points,
                               f"{prim.GetPath()}.primvars:{name}", 3)[:, :3]  # fmt: skip
        if rgb.shape[1] < 3:
            rgb = np.repeat(rgb[:, :1], 3, axis=1)
        return np.concatenate([rgb, np.ones((len(rgb), 1))], axis=1)

    def _display_material(
        self, path, display, d_interp, opacity, o_interp, counts, indices, n_points, double_sided
    ):
        """A material (and COLOR_0 per corner, or None) from displayColor/displayOpacity."""
        color = display[0] if display is not None and len(display) else np.array([0.18, 0.18, 0.18])
        alpha = float(opacity.reshape(-1)[0]) if opacity is not None and len(opacity) else 1.0
        varying_color = display is not None and len(display) > 1 and d_interp != "constant"
        varying_alpha = opacity is not None and len(opacity) > 1 and o_interp != "constant"
        if not varying_color and not varying_alpha:
            return self._plain_material(
                np.array(color).reshape(-1)[:3], alpha, double_sided, False
            ), None
        corners = len(indices)
        rgb = (
            self._per_corner(
                display, d_interp, counts, indices, n_points, f"{path}.primvars:displayColor", 3
            )[:, :3]
            if varying_color
            else np.repeat(np.array(color).reshape(1, -1)[:, :3], corners, axis=0)
        )
        a = (
            self._per_corner(
                opacity, o_interp, counts, indices, n_points, f"{path}.primvars:displayOpacity", 1
            )[:, :1]
            if varying_alpha
            else np.full((corners, 1), alpha)
        )
        material = self._plain_material(
            (1.0, 1.0, 1.0),
            1.0 if varying_alpha else alpha,
            double_sided,
            "alpha" if varying_alpha else True,
        )
        return material, np.concatenate([rgb, a], axis=1)

    def _primitive(
        self,
        attrs: dict[str, np.ndarray],
        tris: np.ndarray,
        material: int | None,
        displacements: list[np.ndarray] | None = None,
    ) -> dict[str, Any]:
        """Weld identical corners, then one glTF primitive: with `displacements` (one array of
        per-point offsets in metres per morph target), a POSITION morph target for each (the
        `_POINT` attribute says which point each corner is), and a NORMAL one where the
        attributes carry its per-corner normal offsets (`_NORMAL_TARGETk`)."""
        names = sorted(attrs)
        table = np.concatenate([attrs[n].reshape(len(attrs[n]), -1) for n in names], axis=1)
        unique, inverse = np.unique(table, axis=0, return_inverse=True)
        inverse = inverse.reshape(-1)
        out_attrs = {}
        columns = {}
        col = 0
        for n in names:
            width = attrs[n].reshape(len(attrs[n]), -1).shape[1]
            columns[n] = unique[:, col : col + width]
            col += width
            if n.startswith("_"):
                continue
            out_attrs[n] = self.writer.accessor(
                columns[n], bounds=n == "POSITION", joints=n.startswith("JOINTS_")
            )
        primitive: dict[str, Any] = {
            "attributes": out_attrs,
            "indices": self.writer.accessor(inverse[tris], indices=True),
        }
        if displacements is not None:
            point = columns["_POINT"][:, 0].astype(np.int64)
            targets = []
            for k, offsets in enumerate(displacements):
                target = {"POSITION": self.writer.accessor(offsets[point], bounds=True)}
                normal = columns.get(f"_NORMAL_TARGET{k:06d}")
                if normal is not None:
                    target["NORMAL"] = self.writer.accessor(normal)
                targets.append(target)
            primitive["targets"] = targets
        if material is not None:
            primitive["material"] = material
        return primitive

    def gprim(self, prim) -> int:
        """An intrinsic shape tessellated, with normals, as UsdGeom defines it: a Cube (size),
        Sphere (radius), Cylinder and Cone (radius, height, centred on the origin along its
        axis, the cone's apex at +height/2, capped), Cylinder_1 (radiusBottom at -height/2,
        radiusTop at +height/2), Capsule (a cylinder of height and radius with a half sphere at
        each end) and Plane (width x length facing +axis)."""
        from pxr import UsdGeom

        t = self.time
        path = str(prim.GetPath())
        key = ("gprim", path)
        if key in self.meshes:
            return self.meshes[key]

        def get(name: str, default: float) -> float:
            attr = prim.GetAttribute(name)
            value = attr.Get(t) if attr else None
            return float(value if value is not None else default) * self.mpu

        axis = prim.GetAttribute("axis").Get(t) if prim.GetAttribute("axis") else None
        if prim.IsA(UsdGeom.Cube):
            pos, nrm, tris = _box(get("size", 2.0) / 2.0)
        elif prim.IsA(UsdGeom.Sphere):
            pos, nrm, tris = _uv_sphere(get("radius", 1.0), 48, 24)
        elif prim.IsA(UsdGeom.Plane):
            pos, nrm, tris = _plane(get("width", 2.0), get("length", 2.0), axis or "Z")
        elif prim.IsA(UsdGeom.Capsule):
            radius, height = get("radius", 0.5), get("height", 1.0)
            pos, nrm, tris = _on_axis(_capsule(radius, height), axis or "Z")
        else:
            height = get("height", 2.0)
            if prim.IsA(UsdGeom.Cylinder_1):
                bottom, top = get("radiusBottom", 1.0), get("radiusTop", 1.0)
            elif prim.IsA(UsdGeom.Cone):
                bottom, top = get("radius", 1.0), 0.0
            else:
                bottom = top = get("radius", 1.0)
            pos, nrm, tris = _on_axis(_frustum(bottom, top, height), axis or "Z")
        double_sided = bool(UsdGeom.Gprim(prim).GetDoubleSidedAttr().Get(t))
        material = self._material_for(prim, double_sided)
        attrs = {"POSITION": pos, "NORMAL": nrm}
        if material is not None:
            if material.uv_sets:
                self.warn(
                    path,
                    f"a textured material on a {prim.GetTypeName()} gprim, which has no st: "
                    "texture coordinates are 0",
                )
                for i, _name in enumerate(material.uv_sets):
                    attrs[f"TEXCOORD_{i}"] = np.zeros((len(pos), 2))
            if material.color_primvar is not None:  # a shape's primvar is one value
                one = self._primvar_colors(prim, material, np.array([1]), np.array([0]), 1)
                attrs["COLOR_0"] = np.repeat(one[:1], len(pos), axis=0)
            material_index = material.index
        else:
            display, _ = self._primvar(prim, "displayColor")
            opacity, _ = self._primvar(prim, "displayOpacity")
            color = display.reshape(-1, 3)[0] if display is not None else (0.18, 0.18, 0.18)
            alpha = float(opacity.reshape(-1)[0]) if opacity is not None else 1.0
            material_index = self._plain_material(color, alpha, double_sided, False)
        primitive = self._primitive(attrs, tris, material_index)
        index = self.writer.add("meshes", {"name": path, "primitives": [primitive]})
        self.meshes[key] = index
        self.renderables += 1
        return index

    # ------------------------------------------------------------------ cameras
    def camera_of(self, prim) -> int:
        from pxr import UsdGeom

        t = self.time
        path = str(prim.GetPath())
        cam = UsdGeom.Camera(prim)
        focal = float(cam.GetFocalLengthAttr().Get(t))
        h_ap = float(cam.GetHorizontalApertureAttr().Get(t))
        v_ap = float(cam.GetVerticalApertureAttr().Get(t))
        near, far = (float(v) for v in cam.GetClippingRangeAttr().Get(t))
        for name in ("horizontalApertureOffset", "verticalApertureOffset"):
            if float(prim.GetAttribute(name).Get(t) or 0.0) != 0.0:
                self.warn(path, f"{name} (a shifted lens) is not supported")
        if focal <= 0 or h_ap <= 0 or v_ap <= 0:
            field = (
                "focalLength"
                if focal <= 0
                else "horizontalAperture"
                if h_ap <= 0
                else "verticalAperture"
            )
            raise SceneError(f"{path}.{field} must be positive", f"scene:{path}.{field}")
        projection = cam.GetProjectionAttr().Get(t)
        if projection == UsdGeom.Tokens.orthographic:
            # Apertures are in tenths of a scene unit (USD's camera convention).
            camera = {
                "type": "orthographic",
                "orthographic": {
                    "xmag": h_ap * 0.1 * self.mpu / 2.0,
                    "ymag": v_ap * 0.1 * self.mpu / 2.0,
                    "znear": max(near, 0.0) * self.mpu,
                    "zfar": far * self.mpu,
                },
            }
        else:
            camera = {
                "type": "perspective",
                "perspective": {
                    "yfov": 2.0 * math.atan(v_ap / (2.0 * focal)),
                    "aspectRatio": h_ap / v_ap,
                    "znear": max(near, 1e-6) * self.mpu,
                    "zfar": far * self.mpu,
                },
            }
            f_stop = float(cam.GetFStopAttr().Get(t) or 0.0)
            focus = float(cam.GetFocusDistanceAttr().Get(t) or 0.0)
            if f_stop > 0.0 and focus > 0.0:
                self.camera = {
                    "aperture_radius": focal * 0.1 * self.mpu / (2.0 * f_stop),
                    "focus_distance": focus * self.mpu,
                }
                camera["extras"] = dict(self.camera)
        camera["name"] = path
        return self.writer.add("cameras", camera)

    # ------------------------------------------------------------------ lights
    def _emitter_material(self, radiance: np.ndarray, double_sided: bool) -> int:
        key = ("emitter", tuple(round(float(c), 9) for c in radiance), double_sided)
        index = self.plain_materials.get(key)
        if index is None:
            gltf: dict[str, Any] = {
                "name": "UsdLux emitter",
                "pbrMetallicRoughness": {
                    "baseColorFactor": [0.0, 0.0, 0.0, 1.0],
                    "metallicFactor": 0.0,
                    "roughnessFactor": 1.0,
                },
            }
            _set_emission(gltf, [float(c) for c in radiance], self.writer)
            if double_sided:
                gltf["doubleSided"] = True
            index = self.writer.add("materials", gltf)
            self.plain_materials[key] = index
        return index

    def _world_scale(self, prim) -> tuple[float, float, float]:
        from pxr import UsdGeom

        m = np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(self.time)).reshape(4, 4)
        return tuple(float(np.linalg.norm(m[i, :3])) for i in range(3))  # type: ignore[return-value]

    def _shaping(self, prim, path: str) -> tuple[float, float] | None:
        """A light's UsdLuxShapingAPI. A sphere light whose shaping:cone:angle is authored below
        180 degrees is a glTF spot light: (innerConeAngle, outerConeAngle) in radians. outer is
        the cone angle c (at most 90 degrees, glTF's limit: wider is warned and made 90), where
        UsdLux's emission ends. UsdLux's falloff, 1 - smoothstep(c (1 - s), c, angle) with the
        softness s clamped to [0, 1], is one half at h = c (1 - s / 2); glTF's,
        ((cos angle - cos outer) / (cos inner - cos outer))^2, is one half where that ratio is
        1 / sqrt 2, so cos inner = cos c + sqrt 2 (cos h - cos c) gives the spot UsdLux's
        half-intensity angle as well as its cutoff (the curves between differ: docs/scenes.md).
        A hard cone (s = 0) keeps a band of 0.1 % of its angle (glTF's inner angle must be below
        the outer). None for any other light or shaping. What cannot be
        carried is one warning each: shaping:focus, an IES profile, a cone or focus on any
        other light. A cone of 180 degrees or more, without focus or IES, shapes nothing and is
        not warned."""
        from pxr import UsdLux

        if not prim.HasAPI(UsdLux.ShapingAPI):
            return None
        t = self.time
        shaping = UsdLux.ShapingAPI(prim)
        sphere = prim.IsA(UsdLux.SphereLight)
        angle_attr = shaping.GetShapingConeAngleAttr()
        angle = float(angle_attr.Get(t)) if angle_attr.HasAuthoredValue() else 180.0
        cone = sphere and angle < 180.0
        softness = float(shaping.GetShapingConeSoftnessAttr().Get(t) or 0.0)
        focus = float(shaping.GetShapingFocusAttr().Get(t) or 0.0)
        ies = shaping.GetShapingIesFileAttr().Get(t)
        shaped_by = "shaped by its cone only" if cone else "unshaped"
        if ies is not None and ies.path:
            self.warn(path, f"an IES profile ({ies.path}) is not converted: the light is "
                      f"{shaped_by}")  # fmt: skip
        if not sphere:
            if angle < 180.0 or focus > 0.0:
                self.warn(path, f"light shaping (cone, focus) on a {prim.GetTypeName()} is not "
                          "converted: the light is unshaped")  # fmt: skip
            return None
        if focus > 0.0:
            self.warn(path, f"shaping:focus (a cosine-power falloff) is not converted: the "
                      f"light is {shaped_by}")  # fmt: skip
        if not cone:
            return None
        if angle > 90.0:
            self.warn(path, f"a cone of {angle:g} degrees is wider than glTF's spot lights "
                      "(90 degrees at most): rendered as a 90-degree cone")  # fmt: skip
            angle = 90.0
        outer = math.radians(max(angle, 0.0))
        half = outer * (1.0 - min(max(softness, 0.0), 1.0) / 2.0)  # UsdLux's half intensity
        cos_inner = math.cos(outer) + math.sqrt(2.0) * (math.cos(half) - math.cos(outer))
        inner = math.acos(min(cos_inner, 1.0))
        return min(inner, outer * (1.0 - 1e-3)), outer

    def light(self, prim, node: dict[str, Any]) -> None:
        from pxr import UsdLux

        t = self.time
        path = str(prim.GetPath())
        api = UsdLux.LightAPI(prim)
        for name, attr in (("diffuse", api.GetDiffuseAttr()), ("specular", api.GetSpecularAttr())):
            if float(attr.Get(t)) != 1.0:
                self.warn(path, f"inputs:{name} (a per-response multiplier) is not supported")
        cone = self._shaping(prim, path)
        if _links(api.GetLightLinkCollectionAPI()):
            self.warn(path, "light linking is not supported: the light lights everything")
        if _links(api.GetShadowLinkCollectionAPI()):
            self.warn(path, "shadow linking is not supported: everything casts the light's shadows")
        sx, sy, sz = self._world_scale(prim)
        if prim.IsA(UsdLux.RectLight):
            rect = UsdLux.RectLight(prim)
            width, height = float(rect.GetWidthAttr().Get(t)), float(rect.GetHeightAttr().Get(t))
            if rect.GetTextureFileAttr().Get(t):
                self.warn(path, "a rect light's texture is not supported: it emits its colour")
            radiance = light_radiance(prim, t, width * height * sx * sy)
            pos, nrm, tris = _rect(width * self.mpu, height * self.mpu)
            node["mesh"] = self._light_mesh(path, pos, nrm, tris, radiance)
        elif prim.IsA(UsdLux.DiskLight):
            radius = float(UsdLux.DiskLight(prim).GetRadiusAttr().Get(t))
            radiance = light_radiance(prim, t, math.pi * radius * radius * sx * sy)
            pos, nrm, tris = _disk(radius * self.mpu, 64)
            node["mesh"] = self._light_mesh(path, pos, nrm, tris, radiance)
        elif prim.IsA(UsdLux.SphereLight):
            sphere = UsdLux.SphereLight(prim)
            radius = float(sphere.GetRadiusAttr().Get(t))
            scale = (sx * sy * sz) ** (1.0 / 3.0)
            point = sphere.GetTreatAsPointAttr().Get(t) or radius <= 0.0
            if cone is not None:  # a spot: glTF's spots are points
                area = None if point else 4.0 * math.pi * (radius * scale) ** 2
                radiance = light_radiance(prim, t, area)
                r_m = radius * scale * self.mpu
                intensity = radiance * math.pi * r_m * r_m  # candela: L x projected area
                if not point:
                    self.warn(path, f"a shaped sphere light of radius {radius:g} is a spot light "
                              "at its centre (glTF's spot lights are points): its intensity in "
                              "the cone is the sphere's, its shadows are hard and the sphere is "
                              "not seen")  # fmt: skip
                if radius <= 0.0:
                    self.warn(path, "a sphere light of radius 0 emits nothing")
                elif cone[1] <= 0.0:
                    self.warn(path, "a cone of angle 0 emits nothing")
                else:
                    self._punctual(node, "spot", intensity, path, cone)
            elif point:
                radiance = light_radiance(prim, t, None)
                r_m = radius * scale * self.mpu
                intensity = radiance * math.pi * r_m * r_m  # candela: L x projected area
                self._punctual(node, "point", intensity, path)
                if radius <= 0.0:
                    self.warn(path, "a sphere light of radius 0 emits nothing")
            else:
                radiance = light_radiance(prim, t, 4.0 * math.pi * (radius * scale) ** 2)
                pos, nrm, tris = _sphere_light(radius * self.mpu)
                node["mesh"] = self._light_mesh(path, pos, nrm, tris, radiance)
        elif prim.IsA(UsdLux.DistantLight):
            distant = UsdLux.DistantLight(prim)
            angle = math.radians(float(distant.GetAngleAttr().Get(t)))
            radiance = light_radiance(prim, t, None)
            if api.GetNormalizeAttr().Get(t):
                illuminance = radiance
            elif angle > 0.0:
                illuminance = radiance * 2.0 * math.pi * (1.0 - math.cos(angle / 2.0))
            else:
                illuminance = radiance
                self.warn(
                    path,
                    "a distant light of angle 0 without normalize: its intensity is taken as "
                    "the illuminance",
                )
            if angle > 0.0:
                self.warn(
                    path,
                    "the distant light's angle (soft shadows) is not carried: it is a "
                    "directional light",
                )
            self._punctual(node, "directional", illuminance, path)
        elif prim.IsA(UsdLux.DomeLight) or prim.IsA(UsdLux.DomeLight_1):
            self.dome(prim)
        else:
            self.warn(path, f"{prim.GetTypeName()} lights are not converted")

    def dome(self, prim) -> None:
        """A dome light as the job's environment: its .hdr/.exr texture (or, without one, a
        constant map of its radiance), intensity x 2^exposure as environment_intensity, and its
        turn about the up axis as environment_rotation_deg."""
        from pxr import UsdLux

        t = self.time
        path = str(prim.GetPath())
        if self.environment is not None:
            self.warn(path, f"a second dome light; the farm uses {self.environment['prim']}")
            return
        is_1 = prim.IsA(UsdLux.DomeLight_1)
        dome = UsdLux.DomeLight_1(prim) if is_1 else UsdLux.DomeLight(prim)
        fmt = str(dome.GetTextureFormatAttr().Get(t) or "automatic")
        if fmt not in ("automatic", "latlong"):
            self.warn(path, f"a dome texture in the {fmt} format is not supported: no environment")
            return
        api = UsdLux.LightAPI(prim)
        radiance = light_radiance(prim, t, None)
        scale = float(api.GetIntensityAttr().Get(t)) * 2.0 ** float(api.GetExposureAttr().Get(t))
        asset = dome.GetTextureFileAttr().Get(t)
        environment: dict[str, Any] = {"prim": path}
        if asset is not None and asset.path:
            suffix = Path(asset.path).suffix.lower()
            where = f"{path}.inputs:texture:file"
            resolved = packaged_copy(asset.resolvedPath, self.root, self.work, where)
            data = read_inside(resolved, (self.root, self.work / "packaged"), where)
            if suffix in (".hdr", ".exr"):
                environment["data"] = data
                environment["filename"] = Path(asset.path).name
            else:  # an 8-bit image (PNG, JPEG...): decoded to linear radiance as an EXR
                environment["data"] = self._linear_exr(resolved, where)
                environment["filename"] = Path(asset.path).stem + ".exr"
            if np.ptp(radiance / max(scale, 1e-30)) > 1e-6:
                self.warn(
                    path, "a dome's colour or colour temperature is not applied to its texture"
                )
            environment["intensity"] = scale
        else:
            peak = float(np.max(radiance))
            if peak <= 0.0:
                self.warn(path, "the dome light emits nothing")
                return
            environment["data"] = constant_hdr(radiance / peak)
            environment["filename"] = f"{prim.GetName()}.hdr"
            environment["intensity"] = peak
        if environment["intensity"] <= 0.0:
            self.warn(path, "the dome light emits nothing")
            return
        # A constant map looks the same turned any way: nothing to warn about its turn.
        textured = asset is not None and bool(asset.path)
        environment["rotation_deg"] = self._dome_rotation(prim, dome, is_1, warn=textured)
        self.environment = environment
        self.renderables += 1

    def _linear_exr(self, resolved: str, where: str) -> bytes:
        """A low-dynamic-range dome texture as a float EXR the workers read as an environment
        map: its values decoded from sRGB (USD's "auto" colour space of an 8-bit image, as
        Blender's importer reads it too); a single channel repeated, alpha dropped."""
        import OpenImageIO as oiio

        buf = oiio.ImageBuf(resolved)
        if buf.has_error or not buf.initialized:
            raise SceneError(f"{where}: {Path(resolved).name} cannot be read as an image",
                             f"scene:{where}")  # fmt: skip
        pixels = np.asarray(buf.get_pixels(oiio.FLOAT), dtype=np.float64)
        if pixels.ndim == 2:
            pixels = pixels[:, :, None]
        rgb = pixels[:, :, [0, 0, 0]] if pixels.shape[2] < 3 else pixels[:, :, :3]
        if buf.spec().format.basetype in (oiio.UINT8, oiio.UINT16):
            rgb = np.where(rgb <= 0.04045, rgb / 12.92, ((rgb + 0.055) / 1.055) ** 2.4)
        out = self.work / "dome-texture.exr"
        image = oiio.ImageBuf(oiio.ImageSpec(rgb.shape[1], rgb.shape[0], 3, oiio.FLOAT))
        image.set_pixels(oiio.ROI(0, rgb.shape[1], 0, rgb.shape[0], 0, 1, 0, 3),
                         rgb.astype(np.float32))  # fmt: skip
        if not image.write(str(out)):
            raise SceneError(f"{where}: the dome texture could not be re-encoded", f"scene:{where}")
        data = out.read_bytes()
        out.unlink()
        return data

    def _dome_rotation(self, prim, dome, is_1: bool, warn: bool = True) -> float:
        """The farm's environment_rotation_deg for a dome: the farm's map centre looks along
        glTF -Z at 0 and turns about +Y; a USD dome's (OpenEXR latitude-longitude) looks along
        the dome's +Z with its pole on its +Y (DomeLight_1: on poleAxis; "scene", the stage's
        up axis). Its world orientation in glTF space M maps the centre to d, and the rotation r
        with R_y(r) (0, 0, -1) = d is atan2(-d.x, -d.z)."""
        from pxr import UsdGeom

        path = str(prim.GetPath())
        world = np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(self.time))
        rotation = world.reshape(4, 4)[:3, :3].T  # column vectors
        rotation = rotation / np.maximum(np.linalg.norm(rotation, axis=0), 1e-30)
        pole = str(dome.GetPoleAxisAttr().Get(self.time)) if is_1 else "Y"
        if pole == "scene":
            pole = self.up
        align = np.eye(3)
        if pole == "Z":  # dome +Y onto +Z: +90 degrees about X
            align = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
        to_gltf = np.eye(3)
        if self.up == "Z":  # (x, y, z) -> (x, z, -y), as the root node turns the stage
            to_gltf = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])
        m = to_gltf @ rotation @ align
        if np.linalg.det(m) < 0 and warn:
            self.warn(path, "a mirrored dome is rendered unmirrored")
        up = m @ np.array([0.0, 1.0, 0.0])
        if up[1] < 1.0 - 1e-4 and warn:
            self.warn(path, "the dome's pole does not point up: it is rendered with its pole up")
        d = m @ np.array([0.0, 0.0, 1.0])
        return math.degrees(math.atan2(-d[0], -d[2]))

    def _light_mesh(self, path: str, pos, nrm, tris, radiance) -> int:
        material = self._emitter_material(radiance, False)
        primitive = self._primitive({"POSITION": pos, "NORMAL": nrm}, tris, material)
        self.renderables += 1
        return self.writer.add("meshes", {"name": path, "primitives": [primitive]})

    def _punctual(
        self,
        node: dict[str, Any],
        kind: str,
        value: np.ndarray,
        path: str,
        cone: tuple[float, float] | None = None,
    ) -> None:
        peak = float(np.max(value))
        if peak <= 0.0:
            self.warn(path, "the light emits nothing")
            return
        lights = self.writer.doc.setdefault("extensions", {}).setdefault(
            "KHR_lights_punctual", {"lights": []}
        )["lights"]
        light: dict[str, Any] = {
            "name": path,
            "type": kind,
            "color": [float(c) / peak for c in value],
            "intensity": peak,
        }
        if cone is not None:
            light["spot"] = {"innerConeAngle": cone[0], "outerConeAngle": cone[1]}
        lights.append(light)
        node.setdefault("extensions", {})["KHR_lights_punctual"] = {"light": len(lights) - 1}
        self.writer.use_extension("KHR_lights_punctual")
        self.renderables += 1


def _links(collection) -> bool:
    """Whether a light's light- or shadow-link collection leaves anything out: it names prims to
    include or exclude, or its includeRoot is authored false (then it holds its includes
    alone, nothing when there are none)."""
    if not collection:
        return False
    if collection.GetIncludesRel().GetTargets() or collection.GetExcludesRel().GetTargets():
        return True
    root = collection.GetIncludeRootAttr()
    return bool(root and root.HasAuthoredValue() and not root.Get())


def constant_hdr(rgb: np.ndarray, width: int = 8, height: int = 4) -> bytes:
    """A Radiance .hdr of one colour (flat RGBE scanlines): a dome light without a texture."""
    peak = float(np.max(rgb))
    if peak < 1e-32:
        pixel = bytes(4)
    else:
        mantissa, exponent = math.frexp(peak)
        factor = mantissa * 256.0 / peak
        pixel = bytes([*(min(255, int(c * factor)) for c in rgb), exponent + 128])
    header = f"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y {height} +X {width}\n".encode()
    return header + pixel * (width * height)


# ---------------------------------------------------------------------- shapes
def _rect(width: float, height: float):
    """A width x height rectangle in the XY plane whose front face (counter-clockwise) looks
    along -Z, as a UsdLux RectLight emits."""
    x, y = width / 2.0, height / 2.0
    pos = np.array([[-x, -y, 0], [-x, y, 0], [x, y, 0], [x, -y, 0]], dtype=np.float64)
    nrm = np.tile([0.0, 0.0, -1.0], (4, 1))
    return pos, nrm, np.array([[0, 1, 2], [0, 2, 3]])


def _disk(radius: float, segments: int):
    """A disk in the XY plane facing -Z (a UsdLux DiskLight)."""
    a = 2.0 * math.pi * np.arange(segments) / segments
    ring = np.stack([radius * np.cos(a), radius * np.sin(a), np.zeros(segments)], axis=1)
    pos = np.concatenate([[[0.0, 0.0, 0.0]], ring])
    nrm = np.tile([0.0, 0.0, -1.0], (segments + 1, 1))
    i = np.arange(segments)
    # counter-clockwise seen from -Z: centre, next, this
    tris = np.stack([np.zeros(segments, dtype=np.int64), 1 + (i + 1) % segments, 1 + i], axis=1)
    return pos, nrm, tris


def _sphere_light(radius: float, slices: int = 32, stacks: int = 16):
    """A sphere light's emitter: the faceted sphere (_uv_sphere) scaled about its centre so
    that its surface area is the sphere's, 4 pi r^2. An emitter of radiance L gives off
    pi L x its area, and a convex body's projected area averaged over directions is its
    area / 4 (Cauchy), so the facets then emit the sphere's power, pi L 4 pi r^2, and from
    afar its mean intensity L pi r^2, while a camera that sees the light sees UsdLux's radiance
    L on a silhouette that straddles the sphere's (the inscribed facets alone have 0.8 % less
    area and look smaller; raising L instead would keep them small and show a brighter L)."""
    pos, nrm, tris = _uv_sphere(1.0, slices, stacks)
    corners = pos[tris]
    area = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]),
                          axis=1).sum() / 2.0  # fmt: skip
    return pos * (radius * math.sqrt(4.0 * math.pi / area)), nrm, tris


def _uv_sphere(radius: float, slices: int, stacks: int):
    theta = np.linspace(0.0, math.pi, stacks + 1)
    phi = np.linspace(0.0, 2.0 * math.pi, slices + 1)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    nrm = np.stack([np.sin(t) * np.cos(p), np.cos(t), -np.sin(t) * np.sin(p)], axis=-1).reshape(
        -1, 3
    )
    pos = radius * nrm
    tris = []
    for i in range(stacks):
        for j in range(slices):
            a, b = i * (slices + 1) + j, (i + 1) * (slices + 1) + j
            if i != 0:
                tris.append([a, b, a + 1])
            if i != stacks - 1:
                tris.append([a + 1, b, b + 1])
    return pos, nrm, np.array(tris)


SLICES = 48  # facets around a cylinder, cone or capsule


def _ring(radius: float, z: float, normal_r: float, normal_z: float):
    """SLICES + 1 points of a circle about Z (the first repeated) and their normals."""
    phi = np.linspace(0.0, 2.0 * math.pi, SLICES + 1)
    pos = np.stack([radius * np.cos(phi), radius * np.sin(phi), np.full_like(phi, z)], axis=1)
    nrm = np.stack([normal_r * np.cos(phi), normal_r * np.sin(phi), np.full_like(phi, normal_z)], 1)
    return pos, nrm


def _join(rings) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangles between consecutive rings of (points, normals), zero-area ones left out, each
    wound counter-clockwise seen from the side its vertex normals point to (outward)."""
    pos = np.concatenate([p for p, _ in rings])
    nrm = np.concatenate([n for _, n in rings])
    tris = []
    for k in range(len(rings) - 1):
        a, b = k * (SLICES + 1), (k + 1) * (SLICES + 1)
        for j in range(SLICES):
            tris += [[a + j, a + j + 1, b + j + 1], [a + j, b + j + 1, b + j]]
    tris = np.array(tris)
    corners = pos[tris]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    keep = np.linalg.norm(cross, axis=1) > 1e-12 * max(float(np.abs(pos).max()), 1e-30) ** 2
    tris, cross = tris[keep], cross[keep]
    inward = (cross * nrm[tris].sum(axis=1)).sum(axis=1) < 0
    tris[inward] = tris[inward][:, [0, 2, 1]]
    return pos, nrm, tris


def _merge(*parts):
    pos, nrm, tris, offset = [], [], [], 0
    for p, n, t in parts:
        pos.append(p)
        nrm.append(n)
        tris.append(t + offset)
        offset += len(p)
    return np.concatenate(pos), np.concatenate(nrm), np.concatenate(tris)


def _cap(radius: float, z: float, up: float):
    """A disk of radius at height z facing +Z (up 1) or -Z (up -1)."""
    return _join([_ring(0.0, z, 0.0, up), _ring(radius, z, 0.0, up)])


def _frustum(bottom: float, top: float, height: float):
    """A capped cone frustum about Z: radius bottom at -height/2, top at +height/2."""
    h = height / 2.0
    slope = math.hypot(height, bottom - top) or 1.0
    nr, nz = height / slope, (bottom - top) / slope
    parts = [_join([_ring(bottom, -h, nr, nz), _ring(top, h, nr, nz)])]
    if bottom > 0:
        parts.append(_cap(bottom, -h, -1.0))
    if top > 0:
        parts.append(_cap(top, h, 1.0))
    return _merge(*parts)


def _capsule(radius: float, height: float, stacks: int = 12):
    """A cylinder of radius and height about Z with a half sphere on each end."""
    h = height / 2.0
    rings = []
    for k in range(stacks + 1):  # the bottom pole to the equator, then the top's
        theta = -math.pi / 2 + (math.pi / 2) * k / stacks
        rings.append(_ring(radius * math.cos(theta), -h + radius * math.sin(theta),
                           math.cos(theta), math.sin(theta)))  # fmt: skip
    for k in range(stacks + 1):
        theta = (math.pi / 2) * k / stacks
        rings.append(_ring(radius * math.cos(theta), h + radius * math.sin(theta),
                           math.cos(theta), math.sin(theta)))  # fmt: skip
    return _join(rings)


def _on_axis(shape, axis: str):
    """A shape built about Z turned so that Z is `axis` (a cyclic permutation: a rotation)."""
    pos, nrm, tris = shape
    order = {"X": [2, 0, 1], "Y": [1, 2, 0]}.get(str(axis))
    if order is None:
        return pos, nrm, tris
    # Z goes to the axis: new[axis] = old z, and the others follow cyclically.
    return pos[:, order], nrm[:, order], tris


def _plane(width: float, length: float, axis: str):
    """A width x length rectangle facing +axis (UsdGeomPlane: width along x for axis Z or Y,
    along z for X; length along y for Z or X, along z for Y)."""
    u, v = {"X": (2, 1), "Y": (0, 2)}.get(str(axis), (0, 1))
    n = 3 - u - v
    pos = np.zeros((4, 3))
    for i, (su, sv) in enumerate(((-1, -1), (1, -1), (1, 1), (-1, 1))):
        pos[i, u], pos[i, v] = su * width / 2.0, sv * length / 2.0
    nrm = np.zeros((4, 3))
    nrm[:, n] = 1.0
    tris = np.array([[0, 1, 2], [0, 2, 3]])
    cross = np.cross(pos[1] - pos[0], pos[2] - pos[0])
    if cross[n] < 0:
        tris = tris[:, [0, 2, 1]]
    return pos, nrm, tris


def _box(h: float):
    faces = []
    for axis in range(3):
        for sign in (1.0, -1.0):
            n = np.zeros(3)
            n[axis] = sign
            u = np.zeros(3)
            u[(axis + 1) % 3] = 1.0
            v = np.cross(n, u)
            corners = [h * (n + su * u + sv * v) for su, sv in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
            faces.append((corners, n))
    pos = np.array([c for corners, _ in faces for c in corners])
    nrm = np.array([n for _, n in faces for _ in range(4)])
    tris = np.array(
        [[4 * f, 4 * f + 1, 4 * f + 2] for f in range(6)]
        + [[4 * f, 4 * f + 2, 4 * f + 3] for f in range(6)]
    )
    return pos, nrm, tris


def convert_stage(root_layer: Path, root: Path, work: Path) -> Conversion:
    """Check the upload's layers, compose the stage and convert it (see the module's text)."""
    from pxr import Usd

    root = Path(os.path.realpath(root))
    checked = check_layers(root_layer, root)  # its edited layers stay open until composed
    stage = Usd.Stage.Open(str(root_layer), Usd.Stage.LoadAll)
    if stage is None:
        raise SceneError(f"{root_layer.name} cannot be opened as a USD stage")
    check_used_layers(stage, root)  # the defence behind check_layers
    converter = _StageConverter(stage, root, work)
    converter.dropped_materialx(checked.dropped)
    conversion = converter.convert()
    check_used_layers(stage, root)  # value clips' layers open as their values are read
    return conversion


__all__ = ["Conversion", "convert_stage", "light_radiance"]
