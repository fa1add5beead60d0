"""USD to glTF conversion (domain/scenes/usd_convert.py), held to analytic answers.

Stages are built here with usd-core; the GLB is read back with a small reader written here from
the glTF 2.0 specification (node matrices composed parent x child, column-major; accessors read
from the BIN chunk), never with the converter's own helpers. The expected values are worked out
by hand from the USD schemas' definitions (UsdGeomCamera: apertures and focal length in tenths
of a scene unit; UsdLux: radiance = intensity x 2^exposure x color, divided by the world-space
area when normalize is on; KHR_texture_transform's GLSL).
"""

from __future__ import annotations

import json
import math
import shutil
import struct
from pathlib import Path

import numpy as np
import pytest

pxr = pytest.importorskip("pxr")
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdShade  # noqa: E402

from renderfarm.domain.scenes.usd_convert import convert_stage  # noqa: E402
from renderfarm.domain.scenes.usd_materials import texture_transform  # noqa: E402
from renderfarm.errors import SceneError  # noqa: E402

# ------------------------------------------------------------------ a glTF reader (spec-only)

_COMPONENTS = {5126: ("<f4", 4), 5125: ("<u4", 4), 5123: ("<u2", 2), 5121: ("<u1", 1)}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}


def read_glb(glb: bytes) -> tuple[dict, bytes]:
    assert glb[:4] == b"glTF"
    json_len = struct.unpack_from("<I", glb, 12)[0]
    doc = json.loads(glb[20 : 20 + json_len])
    rest = glb[20 + json_len :]
    blob = rest[8 : 8 + struct.unpack_from("<I", rest, 0)[0]] if rest else b""
    return doc, blob


def accessor(doc: dict, blob: bytes, index: int) -> np.ndarray:
    acc = doc["accessors"][index]
    view = doc["bufferViews"][acc["bufferView"]]
    dtype, size = _COMPONENTS[acc["componentType"]]
    width = _WIDTH[acc["type"]]
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    data = np.frombuffer(blob, dtype=dtype, count=acc["count"] * width, offset=start)
    return data.reshape(acc["count"], width) if width > 1 else data


def local_matrix(node: dict) -> np.ndarray:
    if "matrix" in node:
        return np.array(node["matrix"], dtype=np.float64).reshape(4, 4).T  # column-major
    t = np.eye(4)
    t[:3, 3] = node.get("translation", [0, 0, 0])
    x, y, z, w = node.get("rotation", [0, 0, 0, 1])
    r = np.eye(4)
    r[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    s = np.diag([*node.get("scale", [1, 1, 1]), 1.0])
    return t @ r @ s


def world_matrices(doc: dict) -> dict[int, np.ndarray]:
    out: dict[int, np.ndarray] = {}

    def visit(index: int, parent: np.ndarray) -> None:
        m = parent @ local_matrix(doc["nodes"][index])
        out[index] = m
        for child in doc["nodes"][index].get("children", []):
            visit(child, m)

    for root in doc["scenes"][doc.get("scene", 0)]["nodes"]:
        visit(root, np.eye(4))
    return out


def world_triangles(doc: dict, blob: bytes, node_name: str) -> list[np.ndarray]:
    """Each world-space triangle (3 x 3) of every node named `node_name`."""
    tris = []
    for index, m in world_matrices(doc).items():
        node = doc["nodes"][index]
        if node.get("name") != node_name or "mesh" not in node:
            continue
        for prim in doc["meshes"][node["mesh"]]["primitives"]:
            pos = accessor(doc, blob, prim["attributes"]["POSITION"]).astype(np.float64)
            idx = accessor(doc, blob, prim["indices"]).reshape(-1, 3)
            world = (m @ np.c_[pos, np.ones(len(pos))].T).T[:, :3]
            tris += [world[t] for t in idx]
    return tris


def convert(stage: Usd.Stage, root: Path):
    stage.GetRootLayer().Save()
    conversion = convert_stage(Path(stage.GetRootLayer().realPath), root, root)
    doc, blob = read_glb(conversion.glb)
    return conversion, doc, blob


def new_stage(tmp_path: Path, *, meters_per_unit: float = 1.0, up: str = "Y") -> Usd.Stage:
    stage = Usd.Stage.CreateNew(str(tmp_path / "scene.usda"))
    UsdGeom.SetStageMetersPerUnit(stage, meters_per_unit)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z if up == "Z" else UsdGeom.Tokens.y)
    return stage


def unit_cube(stage: Usd.Stage, path: str) -> UsdGeom.Mesh:
    mesh = UsdGeom.Mesh.Define(stage, path)
    h = 0.5
    mesh.CreatePointsAttr([(x, y, z) for z in (-h, h) for y in (-h, h) for x in (-h, h)])
    mesh.CreateFaceVertexCountsAttr([4] * 6)
    mesh.CreateFaceVertexIndicesAttr(
        [0, 2, 3, 1, 4, 5, 7, 6, 0, 1, 5, 4, 2, 6, 7, 3, 0, 4, 6, 2, 1, 3, 7, 5]
    )
    mesh.CreateSubdivisionSchemeAttr("none")
    return mesh


# ------------------------------------------------------------------ transforms and units


def test_a_unit_cube_lands_where_its_transform_units_and_up_axis_put_it(tmp_path):
    """Centimetres, Z up: the cube scaled 2, turned 90 degrees about Z and moved (10, 20, 30)
    cm. A corner (x, y, z) goes to 2 (-y, x, z) + (10, 20, 30) cm, then to metres, then Z-up to
    glTF's Y-up: (X, Y, Z) -> (X, Z, -Y)."""
    stage = new_stage(tmp_path, meters_per_unit=0.01, up="Z")
    xform = UsdGeom.Xform.Define(stage, "/World/Place")
    xform.AddTranslateOp().Set(Gf.Vec3d(10, 20, 30))
    xform.AddRotateZOp().Set(90.0)
    xform.AddScaleOp().Set(Gf.Vec3f(2, 2, 2))
    unit_cube(stage, "/World/Place/Cube")
    conversion, doc, blob = convert(stage, tmp_path)
    triangles = world_triangles(doc, blob, "Cube")
    assert len(triangles) == 12  # six quads, two triangles each
    corners = {tuple(np.round(v, 6)) for t in triangles for v in t}
    expected = set()
    for x in (-0.5, 0.5):
        for y in (-0.5, 0.5):
            for z in (-0.5, 0.5):
                cm = (2 * -y + 10, 2 * x + 20, 2 * z + 30)
                m = [c * 0.01 for c in cm]
                expected.add(tuple(np.round([m[0], m[2], -m[1]], 6)))
    assert corners == expected
    assert conversion.meters_per_unit == 0.01 and conversion.up_axis == "Z"
    # Every triangle faces out of the cube (counter-clockwise seen from outside).
    centre = np.mean([v for t in triangles for v in t], axis=0)
    for t in triangles:
        normal = np.cross(t[1] - t[0], t[2] - t[0])
        assert np.dot(normal, t.mean(axis=0) - centre) > 0


def test_a_subdivision_cage_without_normals_is_smooth_shaded(tmp_path):
    """A Catmull-Clark cube without normals renders as its cage (warned), each corner's
    normal the mean of its three faces' outward normals, (+-1, +-1, +-1) / sqrt(3), as a
    smooth surface is shaded; a cube with subdivisionScheme none gets no NORMAL (glTF's flat
    normals)."""
    stage = new_stage(tmp_path)
    smooth = unit_cube(stage, "/Smooth")
    smooth.CreateSubdivisionSchemeAttr("catmullClark")
    unit_cube(stage, "/Flat")
    conversion, doc, blob = convert(stage, tmp_path)
    assert any(w.startswith("/Smooth: subdivision (catmullClark) is not applied")
               for w in conversion.warnings)  # fmt: skip
    meshes = {n["name"]: doc["meshes"][n["mesh"]] for n in doc["nodes"] if "mesh" in n}
    prim = meshes["Smooth"]["primitives"][0]
    pos = accessor(doc, blob, prim["attributes"]["POSITION"]).astype(np.float64)
    nrm = accessor(doc, blob, prim["attributes"]["NORMAL"]).astype(np.float64)
    assert nrm == pytest.approx(np.sign(pos) / math.sqrt(3.0), abs=1e-6)
    assert "NORMAL" not in meshes["Flat"]["primitives"][0]["attributes"]


def test_a_left_handed_mesh_keeps_its_outward_faces(tmp_path):
    stage = new_stage(tmp_path)
    mesh = unit_cube(stage, "/Cube")
    # The same faces listed the other way round, declared leftHanded: still outward.
    indices = np.array(mesh.GetFaceVertexIndicesAttr().Get()).reshape(6, 4)[:, ::-1]
    mesh.GetFaceVertexIndicesAttr().Set(indices.reshape(-1).tolist())
    mesh.CreateOrientationAttr(UsdGeom.Tokens.leftHanded)
    _, doc, blob = convert(stage, tmp_path)
    triangles = world_triangles(doc, blob, "Cube")
    for t in triangles:
        normal = np.cross(t[1] - t[0], t[2] - t[0])
        assert np.dot(normal, t.mean(axis=0)) > 0


# ------------------------------------------------------------------ cameras


def test_a_cameras_field_of_view_comes_from_its_apertures(tmp_path):
    """yfov = 2 atan(verticalAperture / (2 focalLength)); apertures and focal length in tenths
    of a scene unit, so with centimetres the lens is 50 mm and the aperture radius of f/2 is
    50 mm / (2 x 2) = 12.5 mm; clipping and focus distance in centimetres."""
    stage = new_stage(tmp_path, meters_per_unit=0.01)
    unit_cube(stage, "/Cube")
    camera = UsdGeom.Camera.Define(stage, "/Cam")
    camera.CreateFocalLengthAttr(50.0)
    camera.CreateHorizontalApertureAttr(36.0)
    camera.CreateVerticalApertureAttr(24.0)
    camera.CreateClippingRangeAttr(Gf.Vec2f(1.0, 1000.0))
    camera.CreateFStopAttr(2.0)
    camera.CreateFocusDistanceAttr(250.0)
    conversion, doc, _ = convert(stage, tmp_path)
    (gltf_camera,) = doc["cameras"]
    p = gltf_camera["perspective"]
    assert p["yfov"] == pytest.approx(2 * math.atan(12.0 / 50.0), rel=1e-6)  # 26.99 degrees
    assert p["aspectRatio"] == pytest.approx(1.5)
    assert p["znear"] == pytest.approx(0.01) and p["zfar"] == pytest.approx(10.0)
    assert conversion.camera["aperture_radius"] == pytest.approx(0.0125, rel=1e-6)
    assert conversion.camera["focus_distance"] == pytest.approx(2.5, rel=1e-6)


def test_the_render_settings_camera_is_the_one_kept(tmp_path):
    from pxr import UsdRender

    stage = new_stage(tmp_path)
    unit_cube(stage, "/Cube")
    UsdGeom.Camera.Define(stage, "/A").CreateFocalLengthAttr(20.0)
    UsdGeom.Camera.Define(stage, "/B").CreateFocalLengthAttr(80.0)
    settings = UsdRender.Settings.Define(stage, "/Render/Settings")
    settings.CreateCameraRel().SetTargets([Sdf.Path("/B")])
    stage.SetMetadata("renderSettingsPrimPath", "/Render/Settings")
    conversion, doc, _ = convert(stage, tmp_path)
    (gltf_camera,) = doc["cameras"]
    assert gltf_camera["name"] == "/B"
    assert gltf_camera["perspective"]["yfov"] == pytest.approx(2 * math.atan(15.2908 / 160.0))
    assert any(w.startswith("/A: a second camera") for w in conversion.warnings)


# ------------------------------------------------------------------ lights


def _emitter(doc: dict, blob: bytes, name: str):
    (node,) = [n for n in doc["nodes"] if n.get("name") == name]
    prim = doc["meshes"][node["mesh"]]["primitives"][0]
    material = doc["materials"][prim["material"]]
    strength = material.get("extensions", {}).get("KHR_materials_emissive_strength", {})
    radiance = np.array(material["emissiveFactor"]) * strength.get("emissiveStrength", 1.0)
    return radiance, world_triangles(doc, blob, name), material


def test_a_rect_lights_radiance_comes_from_intensity_exposure_and_area(tmp_path):
    """Normalized: L = intensity x 2^exposure x color / (world width x height). A 2 x 0.5 rect
    scaled 2 has 4 square units: L = 3 x 4 x color / 4. Emitting along its -Z."""
    stage = new_stage(tmp_path)
    unit_cube(stage, "/Cube")
    light = UsdLux.RectLight.Define(stage, "/Key")
    light.CreateWidthAttr(2.0)
    light.CreateHeightAttr(0.5)
    light.CreateIntensityAttr(3.0)
    light.CreateExposureAttr(2.0)
    light.CreateColorAttr(Gf.Vec3f(1.0, 0.5, 0.25))
    light.CreateNormalizeAttr(True)
    light.AddTranslateOp().Set(Gf.Vec3d(0, 3, 0))
    light.AddRotateXOp().Set(-90.0)  # -Z turns to -Y: the light looks down
    light.AddScaleOp().Set(Gf.Vec3f(2, 2, 2))
    _, doc, blob = convert(stage, tmp_path)
    radiance, triangles, material = _emitter(doc, blob, "Key")
    assert radiance == pytest.approx([3.0, 1.5, 0.75], rel=1e-6)
    area = sum(np.linalg.norm(np.cross(t[1] - t[0], t[2] - t[0])) / 2 for t in triangles)
    assert area == pytest.approx(4.0, rel=1e-6)
    for t in triangles:
        normal = np.cross(t[1] - t[0], t[2] - t[0])
        assert normal / np.linalg.norm(normal) == pytest.approx([0, -1, 0], abs=1e-6)
    assert not material.get("doubleSided", False)  # one-sided, as UsdLux's rect light


def test_an_unnormalized_disk_light_emits_intensity_times_two_to_the_exposure(tmp_path):
    stage = new_stage(tmp_path)
    unit_cube(stage, "/Cube")
    light = UsdLux.DiskLight.Define(stage, "/Disk")
    light.CreateRadiusAttr(0.25)
    light.CreateIntensityAttr(5.0)
    light.CreateExposureAttr(-1.0)
    _, doc, blob = convert(stage, tmp_path)
    radiance, triangles, _ = _emitter(doc, blob, "Disk")
    assert radiance == pytest.approx([2.5, 2.5, 2.5], rel=1e-6)
    area = sum(np.linalg.norm(np.cross(t[1] - t[0], t[2] - t[0])) / 2 for t in triangles)
    # A 64-gon inscribed in the circle: (64/2) sin(2 pi / 64) r^2.
    assert area == pytest.approx(32 * math.sin(2 * math.pi / 64) * 0.25**2, rel=1e-6)


@pytest.mark.parametrize(
    ("normalize", "meters_per_unit", "scale"), [(False, 1.0, 1.0), (True, 0.01, 3.0)]
)
def test_a_sphere_lights_facets_emit_the_spheres_power(tmp_path, normalize, meters_per_unit, scale):
    """A Lambertian emitter of radiance L and area A gives off pi L A. The sphere light of
    radius r (world radius R = r x scale x metersPerUnit) gives off pi L 4 pi R^2, with L =
    intensity x 2^exposure (/ (4 pi (r scale)^2) in scene units when normalized): its facets
    must too, within 1e-3, and so, being convex, have the sphere's mean projected area pi R^2
    (area / 4); seen from any direction (their projected area, the sum of the facets' areas
    times their positive cosines), within 1 % of it."""
    stage = new_stage(tmp_path, meters_per_unit=meters_per_unit)
    unit_cube(stage, "/Cube")
    light = UsdLux.SphereLight.Define(stage, "/Bulb")
    radius = 0.2 / meters_per_unit
    light.CreateRadiusAttr(radius)
    light.CreateIntensityAttr(30.0)
    light.CreateExposureAttr(1.0)
    light.CreateNormalizeAttr(normalize)
    light.AddScaleOp().Set(Gf.Vec3f(scale, scale, scale))
    _, doc, blob = convert(stage, tmp_path)
    radiance, triangles, _ = _emitter(doc, blob, "Bulb")
    world_r = radius * scale * meters_per_unit
    expected_l = 30.0 * 2.0
    if normalize:
        expected_l /= 4.0 * math.pi * (radius * scale) ** 2
    assert radiance == pytest.approx([expected_l] * 3, rel=1e-6)
    tris = np.array(triangles)
    cross = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    area = np.linalg.norm(cross, axis=1) / 2.0
    power = math.pi * radiance[0] * area.sum()
    assert power == pytest.approx(math.pi * expected_l * 4.0 * math.pi * world_r**2, rel=1e-3)
    centre = tris.reshape(-1, 3).mean(axis=0)
    outward = ((tris.mean(axis=1) - centre) * cross).sum(axis=1) > 0
    assert outward.all()  # emitting outward (glTF's front faces)
    normals = cross / np.linalg.norm(cross, axis=1, keepdims=True)
    directions = np.random.default_rng(7).normal(size=(500, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    projected = (area[None, :] * np.clip(directions @ normals.T, 0.0, None)).sum(axis=1)
    assert projected == pytest.approx(np.full(500, math.pi * world_r**2), rel=0.01)


def test_a_distant_light_is_a_directional_light_of_its_illuminance(tmp_path):
    """Unnormalized, a distant light is a disk of radiance L filling the cone of its angle:
    illuminance L x 2 pi (1 - cos(angle / 2)). Normalized, intensity is the illuminance."""
    stage = new_stage(tmp_path)
    unit_cube(stage, "/Cube")
    sun = UsdLux.DistantLight.Define(stage, "/Sun")
    sun.CreateIntensityAttr(1000.0)
    sun.CreateAngleAttr(10.0)
    lamp = UsdLux.DistantLight.Define(stage, "/Lamp")
    lamp.CreateIntensityAttr(7.0)
    lamp.CreateNormalizeAttr(True)
    _, doc, _ = convert(stage, tmp_path)
    lights = {li["name"]: li for li in doc["extensions"]["KHR_lights_punctual"]["lights"]}
    expected = 1000.0 * 2 * math.pi * (1 - math.cos(math.radians(5.0)))
    assert lights["/Sun"]["type"] == "directional"
    assert lights["/Sun"]["intensity"] == pytest.approx(expected, rel=1e-6)
    assert lights["/Lamp"]["intensity"] == pytest.approx(7.0)


def _gltf_spot_falloff(cos_angle, light: dict) -> np.ndarray:
    """KHR_lights_punctual's spot attenuation, as its specification writes it (without the
    max(0.001, ...) guard, which no cone here reaches)."""
    spot = light["spot"]
    cos_outer = math.cos(spot.get("outerConeAngle", math.pi / 4))
    cos_inner = math.cos(spot.get("innerConeAngle", 0.0))
    scale = 1.0 / (cos_inner - cos_outer)
    return np.clip(cos_angle * scale - cos_outer * scale, 0.0, 1.0) ** 2


def _usdlux_cone(angle, cone_deg: float, softness: float) -> np.ndarray:
    """UsdLuxShapingAPI's cone: 1 - smoothstep(c (1 - softness), c, angle), 0 beyond c."""
    c = math.radians(cone_deg)
    start = c * (1.0 - softness)
    x = np.clip((angle - start) / max(c - start, 1e-300), 0.0, 1.0)
    return np.where(angle > c, 0.0, 1.0 - x * x * (3.0 - 2.0 * x))


def _lights(doc: dict) -> dict[str, dict]:
    return {li["name"]: li for li in doc["extensions"]["KHR_lights_punctual"]["lights"]}


@pytest.mark.parametrize("softness", [0.0, 0.25, 0.5, 0.75, 1.0])
def test_a_sphere_light_with_a_cone_is_a_spot_of_usdluxs_irradiance(tmp_path, softness):
    """A treatAsPoint sphere light of radius r and radiance L, shaped by a 30-degree cone, is
    a spot of intensity L pi r^2 along its -Z. The irradiance it gives a floor 2 m below,
    from glTF's spot formula on the converted light, against UsdLux's (the same intensity
    times 1 - smoothstep over the cone's soft band): the same where UsdLux is at full
    intensity and beyond the cone (0), one half at UsdLux's half-intensity angle, and within
    0.21 of the axis's between (glTF's curve is quadratic in the cosine)."""
    stage = new_stage(tmp_path)
    unit_cube(stage, "/Cube")
    light = UsdLux.SphereLight.Define(stage, "/Spot")
    light.CreateRadiusAttr(0.05)
    light.CreateTreatAsPointAttr(True)
    light.CreateIntensityAttr(1000.0)
    light.CreateColorAttr(Gf.Vec3f(1.0, 0.5, 0.25))
    light.AddTranslateOp().Set(Gf.Vec3d(0, 2, 0))
    light.AddRotateXOp().Set(-90.0)  # -Z turns to -Y: the cone looks down
    shaping = UsdLux.ShapingAPI.Apply(light.GetPrim())
    shaping.CreateShapingConeAngleAttr(30.0)
    shaping.CreateShapingConeSoftnessAttr(softness)
    conversion, doc, _ = convert(stage, tmp_path)
    assert not [w for w in conversion.warnings if w.startswith("/Spot")], conversion.warnings
    spot = _lights(doc)["/Spot"]
    assert spot["type"] == "spot"
    intensity = np.array(spot["color"]) * spot["intensity"]
    assert intensity == pytest.approx(1000.0 * math.pi * 0.05**2 * np.array([1, 0.5, 0.25]))
    node = next(n for n in doc["nodes"] if n.get("name") == "Spot")
    world = world_matrices(doc)[doc["nodes"].index(node)]
    assert world[:3, 3] == pytest.approx([0, 2, 0], abs=1e-9)
    assert world[:3, :3] @ [0, 0, -1] == pytest.approx([0, -1, 0], abs=1e-9)  # glTF's spot axis
    # The floor y = 0: a point at distance rho from the foot of the light.
    rho = np.linspace(0.0, 2.0, 2001)
    d2 = 4.0 + rho**2
    angle = np.arctan2(rho, 2.0)
    incidence = 2.0 / np.sqrt(d2)
    gltf = spot["intensity"] * _gltf_spot_falloff(np.cos(angle), spot) * incidence / d2
    usd = 1000.0 * math.pi * 0.05**2 * _usdlux_cone(angle, 30.0, softness) * incidence / d2
    axis = 1000.0 * math.pi * 0.05**2 / 4.0
    full = angle <= math.radians(30.0) * (1.0 - softness)
    outside = angle > math.radians(30.0)
    assert gltf[outside] == pytest.approx(0.0, abs=1e-12)
    if softness == 0.0:  # a hard edge: glTF's band is 0.1 % of the angle
        full = angle <= math.radians(30.0) * 0.999
        assert gltf[full] == pytest.approx(usd[full], rel=1e-6)
        assert gltf[~full & ~outside].max() <= usd[~full & ~outside].max()
        return
    assert gltf[full] == pytest.approx(usd[full], rel=1e-6)
    assert np.max(np.abs(gltf - usd)) < 0.21 * axis
    half = math.radians(30.0) * (1.0 - softness / 2.0)
    if softness < 1.0:
        assert _gltf_spot_falloff(np.cos(half), spot) == pytest.approx(0.5, abs=1e-9)
    else:  # glTF's inner angle cannot go below 0: a falloff from the axis, as UsdLux's
        assert spot["spot"]["innerConeAngle"] == 0.0


def test_a_shaped_sphere_with_a_radius_is_a_spot_with_the_spheres_power(tmp_path):
    """Normalized, a sphere of radius r has L = intensity / (4 pi r^2); from afar it is a
    source of intensity L pi r^2 = intensity / 4 in every direction, which the spot keeps in
    its cone (warned: glTF's spots are points)."""
    stage = new_stage(tmp_path)
    unit_cube(stage, "/Cube")
    light = UsdLux.SphereLight.Define(stage, "/Ball")
    light.CreateRadiusAttr(0.3)
    light.CreateIntensityAttr(8.0)
    light.CreateNormalizeAttr(True)
    UsdLux.ShapingAPI.Apply(light.GetPrim()).CreateShapingConeAngleAttr(45.0)
    conversion, doc, _ = convert(stage, tmp_path)
    spot = _lights(doc)["/Ball"]
    assert spot["type"] == "spot" and spot["intensity"] == pytest.approx(2.0)
    assert spot["spot"]["outerConeAngle"] == pytest.approx(math.pi / 4)
    assert any(w.startswith("/Ball: a shaped sphere light of radius 0.3 is a spot light")
               for w in conversion.warnings)  # fmt: skip
    assert not [n for n in doc["nodes"] if n.get("name") == "Ball" and "mesh" in n]


def test_shaping_that_cannot_be_carried_is_one_warning_each_by_prim_path(tmp_path):
    """IES profiles, focus, a cone on a rect light and a cone wider than glTF's 90 degrees are
    warned; a cone of 180 degrees on a distant light (as the Working Group's assets author
    it) shapes nothing and is not."""
    stage = new_stage(tmp_path)
    unit_cube(stage, "/Cube")
    (tmp_path / "lamp.ies").write_text("IESNA:LM-63-2002\n")
    rect = UsdLux.RectLight.Define(stage, "/Rect")
    rect_shaping = UsdLux.ShapingAPI.Apply(rect.GetPrim())
    rect_shaping.CreateShapingConeAngleAttr(40.0)
    rect_shaping.CreateShapingIesFileAttr(Sdf.AssetPath("./lamp.ies"))
    wide = UsdLux.SphereLight.Define(stage, "/Wide")
    wide.CreateTreatAsPointAttr(True)
    wide_shaping = UsdLux.ShapingAPI.Apply(wide.GetPrim())
    wide_shaping.CreateShapingConeAngleAttr(120.0)
    wide_shaping.CreateShapingFocusAttr(2.0)
    sun = UsdLux.DistantLight.Define(stage, "/Sun")
    sun.CreateAngleAttr(0.0)
    sun.CreateNormalizeAttr(True)
    UsdLux.ShapingAPI.Apply(sun.GetPrim()).CreateShapingConeAngleAttr(180.0)
    conversion, doc, _ = convert(stage, tmp_path)
    warned = {p: [w for w in conversion.warnings if w.startswith(p + ":")]
              for p in ("/Rect", "/Wide", "/Sun")}  # fmt: skip
    assert len(warned["/Rect"]) == 2, warned
    assert any("IES profile (./lamp.ies)" in w for w in warned["/Rect"])
    assert any("light shaping (cone, focus) on a RectLight" in w for w in warned["/Rect"])
    assert len(warned["/Wide"]) == 2, warned
    assert any("shaping:focus" in w for w in warned["/Wide"])
    assert any("a cone of 120 degrees" in w for w in warned["/Wide"])
    assert warned["/Sun"] == []
    assert _lights(doc)["/Wide"]["spot"]["outerConeAngle"] == pytest.approx(math.pi / 2)


# ------------------------------------------------------------------ materials


def _material(stage: Usd.Stage, path: str, **inputs) -> UsdShade.Material:
    material = UsdShade.Material.Define(stage, path)
    shader = UsdShade.Shader.Define(stage, f"{path}/Surface")
    shader.CreateIdAttr("UsdPreviewSurface")
    types = {tuple: Sdf.ValueTypeNames.Color3f, float: Sdf.ValueTypeNames.Float}
    for name, value in inputs.items():
        kind = Sdf.ValueTypeNames.Int if name == "useSpecularWorkflow" else types[type(value)]
        shader.CreateInput(name, kind).Set(value)
    material.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
    return material


def test_geom_subsets_bind_their_own_materials(tmp_path):
    stage = new_stage(tmp_path)
    mesh = UsdGeom.Mesh.Define(stage, "/Two")
    mesh.CreatePointsAttr([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (2, 0, 0), (2, 1, 0)])
    mesh.CreateFaceVertexCountsAttr([4, 4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3, 1, 4, 5, 2])
    red = _material(stage, "/Looks/Red", diffuseColor=(1.0, 0.0, 0.0))
    blue = _material(stage, "/Looks/Blue", diffuseColor=(0.0, 0.0, 1.0))
    binding = UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim())
    for name, faces, material in (("left", [0], red), ("right", [1], blue)):
        subset = binding.CreateMaterialBindSubset(name, faces)
        UsdShade.MaterialBindingAPI.Apply(subset.GetPrim()).Bind(material)
    _, doc, blob = convert(stage, tmp_path)
    (mesh_doc,) = doc["meshes"]
    by_colour = {}
    for prim in mesh_doc["primitives"]:
        colour = tuple(
            doc["materials"][prim["material"]]["pbrMetallicRoughness"]["baseColorFactor"]
        )
        pos = accessor(doc, blob, prim["attributes"]["POSITION"])
        by_colour[colour[:3]] = pos[:, 0].mean()
    assert by_colour[(1.0, 0.0, 0.0)] == pytest.approx(0.5)  # the left quad, x in [0, 1]
    assert by_colour[(0.0, 0.0, 1.0)] == pytest.approx(1.5)  # the right quad, x in [1, 2]


def test_a_full_purpose_binding_wins_over_the_all_purpose_one(tmp_path):
    """UsdShade's binding purposes: a final render uses material:binding:full where one is
    authored and the all-purpose material:binding otherwise (the Standard Shader Ball binds its
    walls with :full only)."""
    stage = new_stage(tmp_path)
    red = _material(stage, "/Looks/Red", diffuseColor=(1.0, 0.0, 0.0))
    blue = _material(stage, "/Looks/Blue", diffuseColor=(0.0, 0.0, 1.0))
    only_full = unit_cube(stage, "/OnlyFull")
    UsdShade.MaterialBindingAPI.Apply(only_full.GetPrim()).Bind(
        red, materialPurpose=UsdShade.Tokens.full
    )
    both = unit_cube(stage, "/Both")
    both.AddTranslateOp().Set(Gf.Vec3d(3, 0, 0))
    binding = UsdShade.MaterialBindingAPI.Apply(both.GetPrim())
    binding.Bind(blue)
    binding.Bind(red, materialPurpose=UsdShade.Tokens.full)
    only_all = unit_cube(stage, "/OnlyAll")
    only_all.AddTranslateOp().Set(Gf.Vec3d(6, 0, 0))
    UsdShade.MaterialBindingAPI.Apply(only_all.GetPrim()).Bind(blue)
    _, doc, _ = convert(stage, tmp_path)
    colours = {}
    for node in doc["nodes"]:
        if "mesh" in node:
            (prim,) = doc["meshes"][node["mesh"]]["primitives"]
            factor = doc["materials"][prim["material"]]["pbrMetallicRoughness"]
            colours[node["name"]] = tuple(factor["baseColorFactor"][:3])
    assert colours == {
        "OnlyFull": (1.0, 0.0, 0.0),
        "Both": (1.0, 0.0, 0.0),
        "OnlyAll": (0.0, 0.0, 1.0),
    }, colours


def test_preview_surface_factors_opacity_and_workflows(tmp_path):
    stage = new_stage(tmp_path)
    cases = {
        "Metal": dict(diffuseColor=(0.9, 0.6, 0.2), metallic=1.0, roughness=0.25),
        "Coat": dict(clearcoat=0.7, clearcoatRoughness=0.1, ior=1.33),
        "Glow": dict(emissiveColor=(4.0, 2.0, 0.0)),
        "Mask": dict(opacity=0.2, opacityThreshold=0.5),
        "Veil": dict(opacity=0.3),
        # F0 of ior 1.5 is 0.04: a specularColor of 0.02 is half of it.
        "Plastic": dict(useSpecularWorkflow=1, specularColor=(0.02, 0.02, 0.02)),
        "Gold": dict(useSpecularWorkflow=1, specularColor=(1.0, 0.8, 0.3)),
    }
    for i, (name, inputs) in enumerate(cases.items()):
        mesh = unit_cube(stage, f"/{name}Cube")
        mesh.AddTranslateOp().Set(Gf.Vec3d(2 * i, 0, 0))
        UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(
            _material(stage, f"/Looks/{name}", **inputs)
        )
    _, doc, _ = convert(stage, tmp_path)
    m = {mat["name"].rsplit("/", 1)[-1]: mat for mat in doc["materials"]}
    pbr = m["Metal"]["pbrMetallicRoughness"]
    assert pbr["baseColorFactor"] == pytest.approx([0.9, 0.6, 0.2, 1.0], rel=1e-6)
    assert (pbr["metallicFactor"], pbr["roughnessFactor"]) == pytest.approx((1.0, 0.25))
    coat = m["Coat"]["extensions"]
    assert coat["KHR_materials_clearcoat"]["clearcoatFactor"] == pytest.approx(0.7)
    assert coat["KHR_materials_clearcoat"]["clearcoatRoughnessFactor"] == pytest.approx(0.1)
    assert coat["KHR_materials_ior"]["ior"] == pytest.approx(1.33)
    glow = m["Glow"]
    strength = glow["extensions"]["KHR_materials_emissive_strength"]["emissiveStrength"]
    assert np.array(glow["emissiveFactor"]) * strength == pytest.approx([4.0, 2.0, 0.0])
    assert m["Mask"]["alphaMode"] == "MASK" and m["Mask"]["alphaCutoff"] == pytest.approx(0.5)
    assert m["Veil"]["alphaMode"] == "BLEND"
    assert m["Veil"]["pbrMetallicRoughness"]["baseColorFactor"][3] == pytest.approx(0.3)
    # The specular workflow's specularColor is F0: KHR_materials_specular's F0 =
    # min(0.04 x specularColorFactor, 1) must give it back, for a plastic and a metal alike.
    for name, want in (("Plastic", [0.02] * 3), ("Gold", [1.0, 0.8, 0.3])):
        mat = m[name]
        assert mat["pbrMetallicRoughness"]["metallicFactor"] == 0.0
        colour = mat["extensions"]["KHR_materials_specular"]["specularColorFactor"]
        assert [min(0.04 * c, 1.0) for c in colour] == pytest.approx(want, rel=1e-6)
        assert mat["extensions"]["KHR_materials_specular"].get("specularFactor", 1.0) == 1.0


@pytest.mark.parametrize(
    ("scale", "rotation", "translation"),
    [((2.0, 2.0), 0.0, (0.0, 0.0)), ((1.0, 3.0), 30.0, (0.25, -0.5)), ((0.5, 0.5), -90.0, (1, 1))],
)
def test_texture_transform_maps_every_point_as_usd_does(scale, rotation, translation):
    """UsdTransform2d: st' = R(rotation) (scale * st) + translation, st with v up, R
    counter-clockwise; glTF reads uv = (s, 1 - t). KHR_texture_transform (translation *
    rotation * scale) must give uv' = (s', 1 - t'), its rotation r turning uv as
    u' = u cos r + v sin r, v' = -u sin r + v cos r: the reading under which Khronos'
    TextureTransformTest asset shows its arrow on the green marker, as the workers render it
    (and the USD Working Group's conversion of that asset shows its arrow on the green marker
    in usdview and Blender: bench/usd_parity.py, docs/parity.md)."""
    ext = texture_transform(scale[0], scale[1], rotation, translation[0], translation[1])
    off = ext.get("offset", [0.0, 0.0])
    rot = ext.get("rotation", 0.0)
    sc = ext.get("scale", [1.0, 1.0])
    a = math.radians(rotation)
    for s, t in [(0.0, 0.0), (0.3, 0.2), (1.0, 0.7), (-0.4, 1.5)]:
        s2 = math.cos(a) * scale[0] * s - math.sin(a) * scale[1] * t + translation[0]
        t2 = math.sin(a) * scale[0] * s + math.cos(a) * scale[1] * t + translation[1]
        u, v = s, 1.0 - t
        u, v = sc[0] * u, sc[1] * v
        u, v = math.cos(rot) * u + math.sin(rot) * v, -math.sin(rot) * u + math.cos(rot) * v
        u, v = u + off[0], v + off[1]
        assert (u, v) == pytest.approx((s2, 1.0 - t2), abs=1e-9)


def test_the_working_groups_texture_transform_test_gives_khronos_transforms():
    """The USD Working Group's TextureTransformTest is Khronos' glTF TextureTransformTest
    converted: its UsdTransform2d inputs must come back as the glTF asset's own
    KHR_texture_transform values (Rotation: 0.392699 rad; All: offset (-0.2, -0.1), rotation
    0.3, scale 1.5)."""
    rotation = texture_transform(1.0, 1.0, 22.5, 0.38268343, 0.076120496)
    assert rotation["rotation"] == pytest.approx(0.392699, abs=1e-6)
    assert rotation.get("offset", [0.0, 0.0]) == pytest.approx([0.0, 0.0], abs=1e-6)
    everything = texture_transform(1.5, 1.5, 17.188734, 0.24328034, -0.33300462)
    assert everything["rotation"] == pytest.approx(0.3, abs=1e-6)
    assert everything["offset"] == pytest.approx([-0.2, -0.1], abs=1e-6)
    assert everything["scale"] == pytest.approx([1.5, 1.5], abs=1e-6)


def test_textures_st_and_transform_reach_the_gltf(tmp_path):
    import OpenImageIO as oiio

    image = oiio.ImageBuf(oiio.ImageSpec(2, 2, 3, oiio.UINT8))
    image.set_pixels(oiio.ROI(0, 2, 0, 2, 0, 1, 0, 3), np.full((2, 2, 3), 0.5, np.float32))
    assert image.write(str(tmp_path / "wood.png"))
    stage = new_stage(tmp_path)
    mesh = unit_cube(stage, "/Cube")
    st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar(
        "uvmap", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying
    )
    st.Set([(0, 0), (1, 0), (1, 1), (0, 1)] * 6)
    material = _material(stage, "/Looks/Wood")
    surface = UsdShade.Shader(stage.GetPrimAtPath("/Looks/Wood/Surface"))
    reader = UsdShade.Shader.Define(stage, "/Looks/Wood/Reader")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.Token).Set("uvmap")
    place = UsdShade.Shader.Define(stage, "/Looks/Wood/Place")
    place.CreateIdAttr("UsdTransform2d")
    place.CreateInput("in", Sdf.ValueTypeNames.Float2).ConnectToSource(
        reader.ConnectableAPI(), "result"
    )
    place.CreateInput("scale", Sdf.ValueTypeNames.Float2).Set(Gf.Vec2f(4, 4))
    texture = UsdShade.Shader.Define(stage, "/Looks/Wood/Texture")
    texture.CreateIdAttr("UsdUVTexture")
    texture.CreateInput("file", Sdf.ValueTypeNames.Asset).Set("./wood.png")
    texture.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(
        place.ConnectableAPI(), "result"
    )
    texture.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
    surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
        texture.ConnectableAPI(), "rgb"
    )
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)
    _, doc, blob = convert(stage, tmp_path)
    info = doc["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"]
    assert info["extensions"]["KHR_texture_transform"]["scale"] == pytest.approx([4, 4])
    image = doc["images"][doc["textures"][info["index"]]["source"]]
    view = doc["bufferViews"][image["bufferView"]]
    embedded = blob[view["byteOffset"] : view["byteOffset"] + view["byteLength"]]
    assert embedded == (tmp_path / "wood.png").read_bytes()  # the file itself, unchanged
    prim = doc["meshes"][0]["primitives"][0]
    uv = accessor(doc, blob, prim["attributes"]["TEXCOORD_0"])
    assert sorted({tuple(p) for p in uv.tolist()}) == [(0, 0), (0, 1), (1, 0), (1, 1)]


# ------------------------------------------------------------------ instancing


def test_instances_and_point_instancers_share_their_meshes(tmp_path):
    stage = new_stage(tmp_path)
    proto = UsdGeom.Xform.Define(stage, "/Library/Bolt")
    unit_cube(stage, "/Library/Bolt/Body")
    stage.GetPrimAtPath("/Library").SetSpecifier(Sdf.SpecifierClass)
    for i in range(3):
        prim = stage.DefinePrim(f"/World/Bolt{i}", "Xform")
        prim.GetReferences().AddInternalReference("/Library/Bolt")
        prim.SetInstanceable(True)
        UsdGeom.XformCommonAPI(prim).SetTranslate(Gf.Vec3d(3 * i, 0, 0))
    instancer = UsdGeom.PointInstancer.Define(stage, "/World/Scatter")
    ball = UsdGeom.Sphere.Define(stage, "/World/Scatter/Protos/Ball")
    ball.CreateRadiusAttr(0.25)
    instancer.CreatePrototypesRel().SetTargets([ball.GetPath()])
    instancer.CreateProtoIndicesAttr([0, 0, 0, 0])
    instancer.CreatePositionsAttr([(0, 5, 0), (1, 5, 0), (2, 5, 0), (3, 5, 0)])
    del proto
    _, doc, blob = convert(stage, tmp_path)
    assert len(doc["meshes"]) == 2  # one cube, one sphere: instances, not copies
    bodies = [n for n in doc["nodes"] if n.get("name") == "Body"]
    balls = [n for n in doc["nodes"] if n.get("name") == "Ball"]
    assert len(bodies) == 3 and len({n["mesh"] for n in bodies}) == 1
    assert len(balls) == 4 and len({n["mesh"] for n in balls}) == 1
    worlds = world_matrices(doc)
    ball_origins = sorted(
        tuple(np.round(worlds[i][:3, 3], 6))
        for i, n in enumerate(doc["nodes"])
        if n.get("name") == "Ball"
    )
    assert ball_origins == [(x, 5.0, 0.0) for x in (0.0, 1.0, 2.0, 3.0)]
    body_origins = sorted(
        tuple(np.round(worlds[i][:3, 3], 6))
        for i, n in enumerate(doc["nodes"])
        if n.get("name") == "Body"
    )
    assert body_origins == [(x, 0.0, 0.0) for x in (0.0, 3.0, 6.0)]


# ------------------------------------------------------------------ what is refused


def _textured(stage: Usd.Stage, asset: str) -> None:
    mesh = unit_cube(stage, "/World/Cube")
    material = _material(stage, "/World/Looks/M")
    texture = UsdShade.Shader.Define(stage, "/World/Looks/M/Tex")
    texture.CreateIdAttr("UsdUVTexture")
    texture.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(asset)
    surface = UsdShade.Shader(stage.GetPrimAtPath("/World/Looks/M/Surface"))
    surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
        texture.ConnectableAPI(), "rgb"
    )
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)


@pytest.mark.parametrize(
    ("asset", "words"),
    [
        ("/etc/hostname", "absolute"),
        ("../outside.png", "'..'"),
        ("sub/../../outside.png", "'..'"),
        ("https://example.com/t.png", "URL"),
        ("file:///etc/hostname", "URL"),
        ("missing.png", "names no file of the upload"),
        ("pack.usdz[t.png]", "package path"),
    ],
)
def test_an_asset_path_outside_the_upload_is_refused_naming_prim_and_attribute(
    tmp_path, asset, words
):
    root = tmp_path / "upload"
    root.mkdir()
    (tmp_path / "outside.png").write_bytes(b"\x89PNG\r\n\x1a\nsecret")
    stage = new_stage(root)
    _textured(stage, asset)
    with pytest.raises(SceneError) as refused:
        convert(stage, root)
    assert refused.value.field == "scene:/World/Looks/M/Tex.inputs:file"
    assert words in refused.value.message


def test_a_symlink_out_of_the_upload_is_refused(tmp_path):
    root = tmp_path / "upload"
    root.mkdir()
    (root / "link.png").symlink_to("/etc/hostname")
    stage = new_stage(root)
    _textured(stage, "link.png")
    with pytest.raises(SceneError) as refused:
        convert(stage, root)
    assert refused.value.field == "scene:/World/Looks/M/Tex.inputs:file"
    assert "outside the upload" in refused.value.message


@pytest.mark.parametrize("arc", ["sublayer", "reference", "payload"])
def test_a_composition_arc_outside_the_upload_is_refused_before_it_is_opened(tmp_path, arc):
    root = tmp_path / "upload"
    root.mkdir()
    outside = Usd.Stage.CreateNew(str(tmp_path / "outside.usda"))
    unit_cube(outside, "/Thing")
    outside.GetRootLayer().Save()
    stage = new_stage(root)
    unit_cube(stage, "/Cube")
    if arc == "sublayer":
        stage.GetRootLayer().subLayerPaths.append("../outside.usda")
        field = "scene:scene.usda.subLayers[0]"
    elif arc == "reference":
        stage.DefinePrim("/Ref").GetReferences().AddReference(
            str(tmp_path / "outside.usda"), "/Thing"
        )
        field = "scene:/Ref.references"
    else:
        stage.DefinePrim("/Load").GetPayloads().AddPayload("../outside.usda", "/Thing")
        field = "scene:/Load.payload"
    stage.GetRootLayer().Save()
    with pytest.raises(SceneError) as refused:
        convert_stage(root / "scene.usda", root, root)
    assert refused.value.field == field


_MTLX = """<?xml version="1.0"?>
<materialx version="1.38">
  <standard_surface name="SR_red" type="surfaceshader">
    <input name="base_color" type="color3" value="1, 0, 0" />
  </standard_surface>
  <surfacematerial name="Red" type="material">
    <input name="surfaceshader" type="surfaceshader" nodename="SR_red" />
  </surfacematerial>
</materialx>
"""


def _node_material(doc: dict, name: str) -> dict:
    node = next(n for n in doc["nodes"] if n.get("name") == name and "mesh" in n)
    return doc["materials"][doc["meshes"][node["mesh"]]["primitives"][0]["material"]]


@pytest.mark.parametrize("arc", ["reference", "payload", "sublayer", "variant"])
def test_a_materialx_document_composed_as_a_layer_is_dropped_with_one_warning(tmp_path, arc):
    """A stage composing a .mtlx document as a layer (as the USD Working Group's MaterialX
    assets and Houdini's exports do) converts without it: one warning names the prim (the
    layer for a sublayer) and the document, a mesh bound to one of its materials gets the
    default material (0.18 grey: no displayColor), a mesh bound to a UsdPreviewSurface keeps
    its own, and neither the .mtlx (not even XML here) nor the layer's file is read or
    changed."""
    root = tmp_path / "upload"
    (root / "looks").mkdir(parents=True)
    (root / "looks" / "red.mtlx").write_text("not XML: a MaterialX document never opened")
    stage = new_stage(root)
    unit_cube(stage, "/Plain")
    unit_cube(stage, "/Blue").AddTranslateOp().Set(Gf.Vec3d(3, 0, 0))
    blue = _material(stage, "/Looks/Blue", diffuseColor=(0.0, 0.0, 1.0))
    UsdShade.MaterialBindingAPI.Apply(stage.GetPrimAtPath("/Blue")).Bind(blue)
    holder = stage.DefinePrim("/MaterialX", "Scope")
    if arc == "reference":
        holder.GetReferences().AddReference("./looks/red.mtlx", "/MaterialX")
        warned = "/MaterialX: the reference to the MaterialX document ./looks/red.mtlx is dropped"
    elif arc == "payload":
        holder.GetPayloads().AddPayload("./looks/red.mtlx", "/MaterialX")
        warned = "/MaterialX: the payload to the MaterialX document ./looks/red.mtlx is dropped"
    elif arc == "sublayer":
        stage.GetRootLayer().subLayerPaths.append("looks/red.mtlx")
        warned = "scene.usda: the sublayer to the MaterialX document looks/red.mtlx is dropped"
    else:
        looks = holder.GetVariantSets().AddVariantSet("look")
        looks.AddVariant("mtlx")
        looks.SetVariantSelection("mtlx")
        with looks.GetVariantEditContext():
            holder.GetReferences().AddReference("./looks/red.mtlx", "/MaterialX")
        warned = ("/MaterialX: the reference to the MaterialX document ./looks/red.mtlx (in "
                  "variant look=mtlx) is dropped")  # fmt: skip
    plain = UsdShade.MaterialBindingAPI.Apply(stage.GetPrimAtPath("/Plain"))
    plain.GetDirectBindingRel().SetTargets([Sdf.Path("/MaterialX/Materials/Red")])
    stage.GetRootLayer().Save()
    before = (root / "scene.usda").read_bytes()
    conversion = convert_stage(root / "scene.usda", root, tmp_path)
    doc, _ = read_glb(conversion.glb)
    dropped = [w for w in conversion.warnings if "red.mtlx" in w and "is dropped" in w]
    assert len(dropped) == 1, conversion.warnings
    assert dropped[0].startswith(warned)
    if arc != "sublayer":
        assert any(w.startswith("/MaterialX/Materials/Red: a material of the dropped MaterialX")
                   for w in conversion.warnings), conversion.warnings  # fmt: skip
    default = _node_material(doc, "Plain")["pbrMetallicRoughness"]["baseColorFactor"]
    assert default == pytest.approx([0.18, 0.18, 0.18, 1.0])
    own = _node_material(doc, "Blue")["pbrMetallicRoughness"]["baseColorFactor"]
    assert own == pytest.approx([0.0, 0.0, 1.0, 1.0])
    assert (root / "scene.usda").read_bytes() == before


def test_a_materialx_document_outside_the_upload_is_still_refused(tmp_path):
    root = tmp_path / "upload"
    root.mkdir()
    (tmp_path / "red.mtlx").write_text(_MTLX)
    stage = new_stage(root)
    unit_cube(stage, "/Cube")
    stage.DefinePrim("/MaterialX", "Scope").GetReferences().AddReference("../red.mtlx")
    stage.GetRootLayer().Save()
    with pytest.raises(SceneError) as refused:
        convert_stage(root / "scene.usda", root, root)
    assert refused.value.field == "scene:/MaterialX.references"
    assert "climbs out of the upload" in refused.value.message


def test_a_stage_with_nothing_to_render_is_refused_with_what_was_dropped(tmp_path):
    stage = new_stage(tmp_path)
    curves = UsdGeom.BasisCurves.Define(stage, "/Hair")
    curves.CreatePointsAttr([(0, 0, 0), (0, 1, 0), (0, 2, 0), (0, 3, 0)])
    curves.CreateCurveVertexCountsAttr([4])
    with pytest.raises(SceneError) as refused:
        convert(stage, tmp_path)
    assert "nothing to render" in refused.value.message
    assert "/Hair: BasisCurves prims are not converted" in refused.value.message


# ------------------------------------------------------------------ dome lights


def test_a_textured_dome_is_the_environment_turned_as_the_dome_is(tmp_path):
    """The farm's map centre looks along -Z at rotation 0 and turns about +Y: its centre
    direction is R_y(r) (0, 0, -1) = (-sin r, 0, -cos r). A USD dome's latitude-longitude
    centre looks along its +Z; turned 90 degrees about Y it looks along +X, so -sin r = 1:
    r = -90 degrees. Intensity x 2^exposure scales it."""
    import OpenImageIO as oiio

    sky = oiio.ImageBuf(oiio.ImageSpec(8, 4, 3, oiio.FLOAT))
    sky.set_pixels(oiio.ROI(0, 8, 0, 4, 0, 1, 0, 3), np.full((4, 8, 3), 0.25, np.float32))
    assert sky.write(str(tmp_path / "sky.exr"))
    stage = new_stage(tmp_path)
    unit_cube(stage, "/Cube")
    dome = UsdLux.DomeLight.Define(stage, "/Sky")
    dome.CreateTextureFileAttr("./sky.exr")
    dome.CreateIntensityAttr(3.0)
    dome.CreateExposureAttr(1.0)
    dome.AddRotateYOp().Set(90.0)
    conversion, _, _ = convert(stage, tmp_path)
    env = conversion.environment
    assert env["data"] == (tmp_path / "sky.exr").read_bytes() and env["filename"] == "sky.exr"
    assert env["intensity"] == pytest.approx(6.0)
    r = math.radians(env["rotation_deg"])
    assert (-math.sin(r), -math.cos(r)) == pytest.approx((1.0, 0.0), abs=1e-6)


def test_an_8_bit_dome_texture_is_decoded_from_srgb_into_an_exr(tmp_path):
    """An 8-bit PNG dome texture (the USD Working Group's McUsd has one): its texels decoded
    from sRGB, as USD's "auto" colour space reads an 8-bit image, into the EXR the workers
    read; 128 / 255 is ((128 / 255 + 0.055) / 1.055)^2.4 = 0.2158 linear."""
    import OpenImageIO as oiio

    _png(tmp_path / "sky.png", np.full((4, 8, 3), 128 / 255))
    stage = new_stage(tmp_path)
    unit_cube(stage, "/Cube")
    dome = UsdLux.DomeLight.Define(stage, "/Sky")
    dome.CreateTextureFileAttr("./sky.png")
    dome.CreateIntensityAttr(2.0)
    conversion, _, _ = convert(stage, tmp_path)
    env = conversion.environment
    assert env["filename"] == "sky.exr" and env["intensity"] == pytest.approx(2.0)
    (tmp_path / "out.exr").write_bytes(env["data"])
    pixels = oiio.ImageBuf(str(tmp_path / "out.exr")).get_pixels(oiio.FLOAT)
    expected = ((128 / 255 + 0.055) / 1.055) ** 2.4
    assert np.asarray(pixels) == pytest.approx(np.full((4, 8, 3), expected), rel=1e-5)


def test_a_dome_without_a_texture_is_a_constant_map_of_its_radiance(tmp_path):
    import OpenImageIO as oiio

    stage = new_stage(tmp_path)
    unit_cube(stage, "/Cube")
    dome = UsdLux.DomeLight.Define(stage, "/Sky")
    dome.CreateColorAttr(Gf.Vec3f(0.5, 1.0, 0.25))
    dome.CreateIntensityAttr(2.0)
    conversion, _, _ = convert(stage, tmp_path)
    env = conversion.environment
    (tmp_path / "constant.hdr").write_bytes(env["data"])
    pixels = oiio.ImageBuf(str(tmp_path / "constant.hdr")).get_pixels(oiio.FLOAT)
    # Radiance (1, 2, 0.5) = the map's (0.5, 1, 0.25) x intensity 2; RGBE keeps 8 bits.
    assert pixels.reshape(-1, 3) * env["intensity"] == pytest.approx(
        np.tile([1.0, 2.0, 0.5], (pixels.size // 3, 1)), rel=1 / 128
    )
    # USD's centre (+Z) is the farm's centre (-Z) turned half round.
    assert math.cos(math.radians(env["rotation_deg"])) == pytest.approx(-1.0)


def test_a_dome_texture_outside_the_upload_is_refused(tmp_path):
    root = tmp_path / "upload"
    root.mkdir()
    stage = new_stage(root)
    unit_cube(stage, "/Cube")
    UsdLux.DomeLight.Define(stage, "/Sky").CreateTextureFileAttr("/etc/sky.exr")
    with pytest.raises(SceneError) as refused:
        convert(stage, root)
    assert refused.value.field == "scene:/Sky.inputs:texture:file"


# ------------------------------------------------------------------ animation


def _sample(doc: dict, blob: bytes, node: int, path: str, seconds: float) -> np.ndarray | None:
    """A channel's value at `seconds` by glTF's LINEAR rule (Appendix C; slerp for rotation)."""
    for channel in doc["animations"][0]["channels"]:
        if channel["target"] != {"node": node, "path": path}:
            continue
        sampler = doc["animations"][0]["samplers"][channel["sampler"]]
        times = accessor(doc, blob, sampler["input"]).reshape(-1)
        values = accessor(doc, blob, sampler["output"]).astype(np.float64)
        i = int(np.clip(np.searchsorted(times, seconds) - 1, 0, len(times) - 2))
        f = (seconds - times[i]) / (times[i + 1] - times[i])
        a, b = values[i], values[i + 1]
        if path != "rotation":
            return (1 - f) * a + f * b
        d = np.dot(a, b)
        if d < 0:
            b, d = -b, -d
        theta = math.acos(min(1.0, d))
        if theta < 1e-9:
            return a
        return (math.sin((1 - f) * theta) * a + math.sin(f * theta) * b) / math.sin(theta)
    return None


def test_transform_time_samples_become_a_glTF_animation(tmp_path):
    """translate (0,0,0) at frame 0 to (4,0,0) at frame 48, rotateY 0 to 360 degrees over the
    same frames, at 24 time codes per second: at 1 s (frame 24) the cube is at (2, 0, 0) and
    half way round (180 degrees about Y), at 0.5 s at (1, 0, 0) and 90 degrees round."""
    stage = new_stage(tmp_path)
    stage.SetTimeCodesPerSecond(24.0)
    stage.SetStartTimeCode(0.0)
    stage.SetEndTimeCode(48.0)
    cube = unit_cube(stage, "/Spinner")
    move = cube.AddTranslateOp()
    turn = cube.AddRotateYOp()
    move.Set(Gf.Vec3d(0, 0, 0), 0.0)
    move.Set(Gf.Vec3d(4, 0, 0), 48.0)
    turn.Set(0.0, 0.0)
    turn.Set(360.0, 48.0)
    _, doc, blob = convert(stage, tmp_path)
    (node,) = [i for i, n in enumerate(doc["nodes"]) if n.get("name") == "Spinner"]
    assert "matrix" not in doc["nodes"][node]  # glTF: an animated node has TRS
    for seconds, x, degrees in ((0.5, 1.0, 90.0), (1.0, 2.0, 180.0), (1.75, 3.5, 315.0)):
        translation = _sample(doc, blob, node, "translation", seconds)
        assert translation == pytest.approx([x, 0.0, 0.0], abs=1e-6)
        q = _sample(doc, blob, node, "rotation", seconds)
        half = math.radians(degrees) / 2
        expected = np.array([0.0, math.sin(half), 0.0, math.cos(half)])
        assert abs(np.dot(q, expected)) == pytest.approx(1.0, abs=1e-6)  # q and -q: one turn
    times = accessor(doc, blob, doc["animations"][0]["samplers"][0]["input"])
    assert times.min() == 0.0 and times.max() == pytest.approx(2.0)


def _world_at(doc: dict, blob: bytes, seconds: float) -> dict[int, np.ndarray]:
    """Every node's world matrix with the animation's channels sampled at `seconds`."""
    posed = []
    for i, node in enumerate(doc["nodes"]):
        node = dict(node)
        for path in ("translation", "rotation", "scale"):
            value = _sample(doc, blob, i, path, seconds) if "animations" in doc else None
            if value is not None:
                node[path] = list(value)
        posed.append(node)
    return world_matrices({**doc, "nodes": posed})


def test_a_skeleton_and_its_animation_skin_the_mesh(tmp_path):
    """Two joints, root at the origin and tip one unit up; a strip whose top edge is bound to
    the tip. The SkelAnimation turns the tip 90 degrees about Z by frame 24: at 1 s the top
    corners (+-0.5, 2, 0) have turned about the tip's origin (0, 1, 0) to (-1, 1 +- 0.5, 0);
    corners bound to the root stay where they are."""
    from pxr import UsdSkel

    stage = new_stage(tmp_path, meters_per_unit=1.0)
    stage.SetTimeCodesPerSecond(24.0)
    root = UsdSkel.Root.Define(stage, "/Rig")
    skeleton = UsdSkel.Skeleton.Define(stage, "/Rig/Skel")
    joints = ["root", "root/tip"]
    skeleton.CreateJointsAttr(joints)
    up = Gf.Matrix4d().SetTranslate(Gf.Vec3d(0, 1, 0))
    skeleton.CreateBindTransformsAttr([Gf.Matrix4d(1), up])
    skeleton.CreateRestTransformsAttr([Gf.Matrix4d(1), up])
    anim = UsdSkel.Animation.Define(stage, "/Rig/Anim")
    anim.CreateJointsAttr(joints)
    anim.CreateTranslationsAttr([Gf.Vec3f(0, 0, 0), Gf.Vec3f(0, 1, 0)])
    anim.CreateScalesAttr([Gf.Vec3h(1, 1, 1), Gf.Vec3h(1, 1, 1)])
    rotations = anim.CreateRotationsAttr()
    turned = Gf.Quatf(math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4))  # 90 deg about Z
    rotations.Set([Gf.Quatf(1), Gf.Quatf(1)], 0.0)
    rotations.Set([Gf.Quatf(1), turned], 24.0)
    UsdSkel.BindingAPI.Apply(skeleton.GetPrim()).CreateAnimationSourceRel().SetTargets(
        [anim.GetPath()]
    )
    strip = UsdGeom.Mesh.Define(stage, "/Rig/Strip")
    strip.CreatePointsAttr(
        [(-0.5, 0, 0), (0.5, 0, 0), (0.5, 1, 0), (-0.5, 1, 0), (0.5, 2, 0), (-0.5, 2, 0)]
    )
    strip.CreateFaceVertexCountsAttr([4, 4])
    strip.CreateFaceVertexIndicesAttr([0, 1, 2, 3, 3, 2, 4, 5])
    strip.CreateSubdivisionSchemeAttr("none")
    binding = UsdSkel.BindingAPI.Apply(strip.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skeleton.GetPath()])
    binding.CreateJointIndicesPrimvar(False, 1).Set([0, 0, 1, 1, 1, 1])
    binding.CreateJointWeightsPrimvar(False, 1).Set([1.0] * 6)
    del root
    _, doc, blob = convert(stage, tmp_path)
    (node,) = [n for n in doc["nodes"] if n.get("name") == "Strip"]
    skin = doc["skins"][node["skin"]]
    prim = doc["meshes"][node["mesh"]]["primitives"][0]
    pos = accessor(doc, blob, prim["attributes"]["POSITION"]).astype(np.float64)
    joint_ids = accessor(doc, blob, prim["attributes"]["JOINTS_0"])
    weights = accessor(doc, blob, prim["attributes"]["WEIGHTS_0"]).astype(np.float64)
    ibm = accessor(doc, blob, skin["inverseBindMatrices"]).astype(np.float64)
    ibm = [m.reshape(4, 4).T for m in ibm]  # column-major
    for seconds, expected in (
        (0.0, {(-0.5, 2.0, 0.0), (0.5, 2.0, 0.0)}),
        (1.0, {(-1.0, 2.5 - 1.0, 0.0), (-1.0, 0.5, 0.0)}),
    ):
        world = _world_at(doc, blob, seconds)
        skinned = []
        for p, ids, w in zip(pos, joint_ids, weights, strict=True):
            m = sum(wk * world[skin["joints"][j]] @ ibm[j] for j, wk in zip(ids, w, strict=True))
            skinned.append(tuple(np.round((m @ np.r_[p, 1.0])[:3], 5)))
        assert {(-0.5, 0.0, 0.0), (0.5, 0.0, 0.0)} <= set(skinned)  # the root's, unmoved
        top = {s for s, p in zip(skinned, pos, strict=True) if p[1] == 2.0}
        assert top == {tuple(np.round(e, 5)) for e in expected}


def test_a_udim_texture_is_warned_and_its_fallback_used(tmp_path):
    stage = new_stage(tmp_path)
    _textured(stage, "tiles/wood.<UDIM>.png")
    texture = UsdShade.Shader(stage.GetPrimAtPath("/World/Looks/M/Tex"))
    texture.CreateInput("fallback", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(0.2, 0.3, 0.4, 1))
    conversion, doc, _ = convert(stage, tmp_path)
    assert "/World/Looks/M/Tex: UDIM texture sets are not supported" in conversion.warnings[0]
    assert "images" not in doc and "baseColorTexture" not in str(doc["materials"])
    base = doc["materials"][0]["pbrMetallicRoughness"]["baseColorFactor"]
    assert base[:3] == pytest.approx([0.2, 0.3, 0.4], rel=1e-6)  # the texture's fallback


def _png(path: Path, pixels: np.ndarray) -> None:
    import OpenImageIO as oiio

    height, width, channels = pixels.shape
    image = oiio.ImageBuf(oiio.ImageSpec(width, height, channels, oiio.UINT8))
    image.set_pixels(oiio.ROI(0, width, 0, height, 0, 1, 0, channels), pixels.astype(np.float32))
    assert image.write(str(path))


def _connect(stage, material_path: str, name: str, file: str, output: str, type_name, **extra):
    """A UsdUVTexture reading `file` connected to the surface's input `name` via `output`."""
    surface = UsdShade.Shader(stage.GetPrimAtPath(f"{material_path}/Surface"))
    texture = UsdShade.Shader.Define(stage, f"{material_path}/{name}Texture")
    texture.CreateIdAttr("UsdUVTexture")
    texture.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(file)
    for key, value in extra.items():
        texture.CreateInput(key, Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(*value))
    texture.CreateOutput(output, type_name)
    surface.CreateInput(name, type_name).ConnectToSource(texture.ConnectableAPI(), output)


def _embedded(doc: dict, blob: bytes, info: dict, tmp_path: Path) -> np.ndarray:
    import OpenImageIO as oiio

    image = doc["images"][doc["textures"][info["index"]]["source"]]
    view = doc["bufferViews"][image["bufferView"]]
    path = tmp_path / f"embedded-{info['index']}.png"
    path.write_bytes(blob[view["byteOffset"] : view["byteOffset"] + view["byteLength"]])
    return np.asarray(oiio.ImageBuf(str(path)).get_pixels(oiio.FLOAT))


def test_separate_texture_channels_are_packed_as_gltf_reads_them(tmp_path):
    """roughness from one grey image, metallic from another: one metallic-roughness image with
    roughness in G and metallic in B (glTF 3.9.2), R unused (1); the diffuse texture's alpha as
    opacity: the RGBA file itself, BLEND; a normal map with scale 2 and bias -1: normalTexture
    without a warning."""
    rough = np.linspace(0.0, 1.0, 16).reshape(4, 4, 1)
    metal = 1.0 - rough
    _png(tmp_path / "rough.png", rough)
    _png(tmp_path / "metal.png", metal)
    colour = np.concatenate([np.full((4, 4, 3), 0.5), rough], axis=2)
    _png(tmp_path / "colour.png", colour)
    _png(tmp_path / "normal.png", np.tile([0.5, 0.5, 1.0], (4, 4, 1)))
    stage = new_stage(tmp_path)
    mesh = unit_cube(stage, "/Cube")
    st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar(
        "st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying
    )
    st.Set([(0, 0), (1, 0), (1, 1), (0, 1)] * 6)
    material = _material(stage, "/Looks/M")
    float_, colour3 = Sdf.ValueTypeNames.Float, Sdf.ValueTypeNames.Color3f
    _connect(stage, "/Looks/M", "roughness", "rough.png", "r", float_)
    _connect(stage, "/Looks/M", "metallic", "metal.png", "r", float_)
    _connect(stage, "/Looks/M", "diffuseColor", "colour.png", "rgb", colour3)
    _connect(stage, "/Looks/M", "opacity", "colour.png", "a", float_)
    _connect(
        stage, "/Looks/M", "normal", "normal.png", "rgb", Sdf.ValueTypeNames.Normal3f,
        scale=(2, 2, 2, 1), bias=(-1, -1, -1, 0),
    )  # fmt: skip
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)
    conversion, doc, blob = convert(stage, tmp_path)
    assert not [w for w in conversion.warnings if "normal" in w or "packed" in w]
    gltf = doc["materials"][0]
    pbr = gltf["pbrMetallicRoughness"]
    packed = _embedded(doc, blob, pbr["metallicRoughnessTexture"], tmp_path)
    assert packed[:, :, 1] == pytest.approx(rough[:, :, 0], abs=1 / 255)
    assert packed[:, :, 2] == pytest.approx(metal[:, :, 0], abs=1 / 255)
    assert pbr["metallicFactor"] == pbr["roughnessFactor"] == 1.0  # the texture says it all
    base = pbr["baseColorTexture"]
    image = doc["images"][doc["textures"][base["index"]]["source"]]
    view = doc["bufferViews"][image["bufferView"]]
    embedded = blob[view["byteOffset"] : view["byteOffset"] + view["byteLength"]]
    assert embedded == (tmp_path / "colour.png").read_bytes() and gltf["alphaMode"] == "BLEND"
    assert "normalTexture" in gltf


@pytest.mark.parametrize("where", ["variant", "time sample", "asset array", "clip"])
def test_an_escaping_path_anywhere_in_a_layer_is_refused(tmp_path, where):
    """Variants, time samples, asset arrays and value clips are checked as well as plain
    defaults: each names a file outside the upload here."""
    root = tmp_path / "upload"
    root.mkdir()
    stage = new_stage(root)
    unit_cube(stage, "/Cube")
    prim = stage.DefinePrim("/Thing")
    if where == "variant":
        variants = prim.GetVariantSets().AddVariantSet("look")
        variants.AddVariant("dirty")
        variants.SetVariantSelection("dirty")
        with variants.GetVariantEditContext():
            prim.CreateAttribute("texture", Sdf.ValueTypeNames.Asset).Set("../secret.png")
        field = "scene:/Thing.texture"
    elif where == "time sample":
        attr = prim.CreateAttribute("texture", Sdf.ValueTypeNames.Asset)
        attr.Set(Sdf.AssetPath("ok.png"), 1.0)
        attr.Set(Sdf.AssetPath("/etc/hostname"), 2.0)
        field = "scene:/Thing.texture"
    elif where == "asset array":
        attr = prim.CreateAttribute("textures", Sdf.ValueTypeNames.AssetArray)
        attr.Set(Sdf.AssetPathArray([Sdf.AssetPath("ok.png"), Sdf.AssetPath("../x.png")]))
        field = "scene:/Thing.textures"
    else:
        Usd.ClipsAPI(prim).SetClipAssetPaths([Sdf.AssetPath("/tmp/clip.usda")])
        field = "scene:/Thing.clips[default].assetPaths"
    (root / "ok.png").write_bytes(b"\x89PNG\r\n\x1a\n")
    with pytest.raises(SceneError) as refused:
        convert(stage, root)
    assert refused.value.field == field, refused.value.message


def test_point_instancer_positions_over_time_animate_each_instance(tmp_path):
    """Two instances moving from x = 0 and 1 at frame 0 to x = 4 and 7 at frame 24: at 0.5 s
    (frame 12, timeCodesPerSecond 24) they are half way, at x = 2 and 4."""
    stage = new_stage(tmp_path, meters_per_unit=1.0)
    stage.SetTimeCodesPerSecond(24.0)
    stage.SetStartTimeCode(0.0)
    instancer = UsdGeom.PointInstancer.Define(stage, "/Flock")
    bird = UsdGeom.Sphere.Define(stage, "/Flock/Protos/Bird")
    bird.CreateRadiusAttr(0.1)
    instancer.CreatePrototypesRel().SetTargets([bird.GetPath()])
    instancer.CreateProtoIndicesAttr([0, 0])
    positions = instancer.CreatePositionsAttr()
    positions.Set([(0, 0, 0), (1, 0, 0)], 0.0)
    positions.Set([(4, 0, 0), (7, 0, 0)], 24.0)
    _, doc, blob = convert(stage, tmp_path)
    assert len(doc["meshes"]) == 1  # still one shared sphere
    xs = []
    for name in ("Flock[0]", "Flock[1]"):
        (index,) = [i for i, n in enumerate(doc["nodes"]) if n.get("name") == name]
        xs.append(float(_world_at(doc, blob, 0.5)[index][0, 3]))
    assert xs == pytest.approx([2.0, 4.0], abs=1e-6)


def _changing_topology(stage: Usd.Stage, path: str, shapes: dict[float, list]) -> UsdGeom.Mesh:
    """A mesh of one polygon (in the y = 0 plane) that is shapes[t] from time code t on."""
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreateSubdivisionSchemeAttr("none")
    for t, corners in shapes.items():
        mesh.GetPointsAttr().Set([(x, 0.0, z) for x, z in corners], t)
        mesh.GetFaceVertexCountsAttr().Set([len(corners)], t)
        mesh.GetFaceVertexIndicesAttr().Set(list(range(len(corners))), t)
    return mesh


def _visible_at(doc: dict, blob: bytes, node: int, seconds: float) -> bool:
    """KHR_node_visibility's `visible` of a node at a time, by KHR_animation_pointer's rules:
    the channel that points at it, STEP (the last key at or before the time; the first key's
    value before it), else the node's own value."""
    pointer = f"/nodes/{node}/extensions/KHR_node_visibility/visible"
    for animation in doc.get("animations", []):
        for channel in animation["channels"]:
            ext = channel["target"].get("extensions", {}).get("KHR_animation_pointer", {})
            if channel["target"]["path"] != "pointer" or ext.get("pointer") != pointer:
                continue
            sampler = animation["samplers"][channel["sampler"]]
            assert sampler["interpolation"] == "STEP"
            keys = accessor(doc, blob, sampler["input"])
            values = accessor(doc, blob, sampler["output"])
            assert doc["accessors"][sampler["output"]]["componentType"] == 5121
            k = max(int(np.searchsorted(keys, seconds, side="right")) - 1, 0)
            return bool(values[k])
    own = doc["nodes"][node].get("extensions", {}).get("KHR_node_visibility", {})
    return own.get("visible", True)


def test_a_topology_that_changes_is_a_mesh_per_topology_switched_by_visibility(tmp_path):
    """A triangle from time code 1, a quad from 10 (24 per second): two meshes under the
    prim's node, the triangle's area 1/2 and the quad's 1.2^2, each visible (by glTF's rules,
    evaluated here) during its own span alone: the triangle at 0 s, 1/24 s and 9.9/24 s,
    the quad at 10/24 s and after; a still shows the triangle (the start time, 1)."""
    stage = new_stage(tmp_path)
    stage.SetStartTimeCode(1)
    stage.SetEndTimeCode(10)
    stage.SetTimeCodesPerSecond(24)
    quad = [(-0.6, -0.6), (0.6, -0.6), (0.6, 0.6), (-0.6, 0.6)]
    _changing_topology(stage, "/Shape", {1.0: [(0, 0), (1, 0), (0, 1)], 10.0: quad})
    conversion, doc, blob = convert(stage, tmp_path)
    assert not [w for w in conversion.warnings if w.startswith("/Shape")], conversion.warnings
    assert {"KHR_node_visibility", "KHR_animation_pointer"} <= set(doc["extensionsRequired"])
    (parent,) = [n for n in doc["nodes"] if n.get("name") == "Shape"]
    children = parent["children"]
    assert [doc["nodes"][c]["name"] for c in children] == ["Shape@1", "Shape@10"]
    areas = []
    for c in children:
        tris = np.array(world_triangles(doc, blob, doc["nodes"][c]["name"]))
        cross = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
        areas.append(np.linalg.norm(cross, axis=1).sum() / 2.0)
    assert areas == pytest.approx([0.5, 1.44], rel=1e-6)
    triangle, square = children
    for seconds, shown in ((0.0, triangle), (1 / 24, triangle), (9.9 / 24, triangle),
                           (10 / 24, square), (2.0, square)):  # fmt: skip
        assert _visible_at(doc, blob, shown, seconds)
        other = square if shown == triangle else triangle
        assert not _visible_at(doc, blob, other, seconds)
    assert doc["nodes"][triangle]["extensions"]["KHR_node_visibility"]["visible"] is True
    assert doc["nodes"][square]["extensions"]["KHR_node_visibility"]["visible"] is False


def test_more_topologies_than_the_cap_are_thinned_with_a_warning(tmp_path):
    """70 topologies (a polygon of 3 + k % 5 corners, growing, at each time code k): 64
    meshes kept, the first and the last among them, one shown at any time."""
    stage = new_stage(tmp_path)
    shapes = {}
    for k in range(70):
        n = 3 + k % 5
        a = 2 * np.pi * np.arange(n) / n
        shapes[float(k)] = [(float((1 + k) * np.cos(x)), float((1 + k) * np.sin(x))) for x in a]
    _changing_topology(stage, "/Blob", shapes)
    conversion, doc, blob = convert(stage, tmp_path)
    assert any(w.startswith("/Blob: 70 topologies over time: thinned to 64")
               for w in conversion.warnings)  # fmt: skip
    (parent,) = [n for n in doc["nodes"] if n.get("name") == "Blob"]
    names = [doc["nodes"][c]["name"] for c in parent["children"]]
    assert len(names) == 64 and names[0] == "Blob@0" and names[-1] == "Blob@69"
    for seconds in (0.0, 10 / 24, 33.5 / 24, 69 / 24, 80 / 24):
        shown = [c for c in parent["children"] if _visible_at(doc, blob, c, seconds)]
        assert len(shown) == 1


def test_deforming_points_become_morph_targets_played_by_the_animation(tmp_path):
    """A quad whose corner (1, 1, 0) rises to z = 2 by frame 24 (24 time codes a second) and
    back to 0 at frame 48, inside a moved Xform: at 0.5 s the corner is at z = 1, at 1.5 s at
    z = 1 again, the other corners never move. glTF: POSITION + sum of weight_k x target_k, the
    weights sampled LINEAR from the weights channel."""
    stage = new_stage(tmp_path, meters_per_unit=1.0)
    stage.SetTimeCodesPerSecond(24.0)
    stage.SetStartTimeCode(0.0)
    UsdGeom.Xform.Define(stage, "/Moved").AddTranslateOp().Set(Gf.Vec3d(5, 0, 0))
    quad = UsdGeom.Mesh.Define(stage, "/Moved/Sheet")
    quad.CreateFaceVertexCountsAttr([4])
    quad.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    quad.CreateSubdivisionSchemeAttr("none")
    flat = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)]
    raised = [(0, 0, 0), (1, 0, 0), (1, 1, 2), (0, 1, 0)]
    points = quad.CreatePointsAttr()
    points.Set(flat, 0.0)
    points.Set(raised, 24.0)
    points.Set(flat, 48.0)
    _, doc, blob = convert(stage, tmp_path)
    (node_index,) = [i for i, n in enumerate(doc["nodes"]) if n.get("name") == "Sheet"]
    prim = doc["meshes"][doc["nodes"][node_index]["mesh"]]["primitives"][0]
    base = accessor(doc, blob, prim["attributes"]["POSITION"]).astype(np.float64)
    targets = [accessor(doc, blob, t["POSITION"]).astype(np.float64) for t in prim["targets"]]
    (channel,) = [c for c in doc["animations"][0]["channels"] if c["target"]["path"] == "weights"]
    assert channel["target"]["node"] == node_index
    sampler = doc["animations"][0]["samplers"][channel["sampler"]]
    times = accessor(doc, blob, sampler["input"]).reshape(-1)
    weights = accessor(doc, blob, sampler["output"]).reshape(len(times), len(targets))
    for seconds, lift in ((0.0, 0.0), (0.5, 1.0), (1.0, 2.0), (1.5, 1.0), (2.0, 0.0)):
        w = np.array([np.interp(seconds, times, weights[:, k]) for k in range(len(targets))])
        posed = base + sum(wk * t for wk, t in zip(w, targets, strict=True))
        corners = {tuple(np.round(p, 6)) for p in posed}
        assert corners == {(0, 0, 0), (1, 0, 0), (1, 1, lift), (0, 1, 0)}, seconds
    world = world_matrices(doc)[node_index]
    assert world[:3, 3] == pytest.approx([5.0, 0.0, 0.0])  # the parent still places it


def _morph_weights(doc: dict, blob: bytes, node_index: int, count: int):
    """(times in seconds, weights per time) of the weights channel of a node."""
    (channel,) = [c for c in doc["animations"][0]["channels"]
                  if c["target"] == {"node": node_index, "path": "weights"}]  # fmt: skip
    sampler = doc["animations"][0]["samplers"][channel["sampler"]]
    times = accessor(doc, blob, sampler["input"]).reshape(-1).astype(np.float64)
    weights = accessor(doc, blob, sampler["output"]).astype(np.float64)
    return times, weights.reshape(len(times), count)


def _blend_shape_quad(stage, *, inbetween: bool = False):
    """A quad bound to a one-joint skeleton with two blend shapes: "lift" raises corner 2 by
    (0, 0, 2) (sparse: pointIndices [2]), "widen" moves corners 1 and 2 by (1, 0, 0) (dense).
    The SkelAnimation names them in the other order, ["widen", "lift"], with weights
    (0, 0) at frame 0 and (0.5, 1) at frame 24, at 24 time codes a second."""
    from pxr import UsdSkel

    stage.SetTimeCodesPerSecond(24.0)
    stage.SetStartTimeCode(0.0)
    UsdSkel.Root.Define(stage, "/Rig")
    skeleton = UsdSkel.Skeleton.Define(stage, "/Rig/Skel")
    skeleton.CreateJointsAttr(["root"])
    skeleton.CreateBindTransformsAttr([Gf.Matrix4d(1)])
    skeleton.CreateRestTransformsAttr([Gf.Matrix4d(1)])
    anim = UsdSkel.Animation.Define(stage, "/Rig/Anim")
    anim.CreateBlendShapesAttr(["widen", "lift"])
    weights = anim.CreateBlendShapeWeightsAttr()
    weights.Set([0.0, 0.0], 0.0)
    weights.Set([0.5, 1.0], 24.0)
    UsdSkel.BindingAPI.Apply(skeleton.GetPrim()).CreateAnimationSourceRel().SetTargets(
        [anim.GetPath()]
    )
    quad = UsdGeom.Mesh.Define(stage, "/Rig/Sheet")
    quad.CreatePointsAttr([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)])
    quad.CreateFaceVertexCountsAttr([4])
    quad.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    quad.CreateSubdivisionSchemeAttr("none")
    lift = UsdSkel.BlendShape.Define(stage, "/Rig/Sheet/Lift")
    lift.CreateOffsetsAttr([Gf.Vec3f(0, 0, 2)])
    lift.CreatePointIndicesAttr([2])
    if inbetween:
        lift.CreateInbetween("half").SetOffsets([Gf.Vec3f(0, 0, 1.5)])
    widen = UsdSkel.BlendShape.Define(stage, "/Rig/Sheet/Widen")
    widen.CreateOffsetsAttr([Gf.Vec3f(0, 0, 0), Gf.Vec3f(1, 0, 0), Gf.Vec3f(1, 0, 0),
                             Gf.Vec3f(0, 0, 0)])  # fmt: skip
    binding = UsdSkel.BindingAPI.Apply(quad.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skeleton.GetPath()])
    binding.CreateBlendShapesAttr(["lift", "widen"])
    binding.CreateBlendShapeTargetsRel().SetTargets([lift.GetPath(), widen.GetPath()])
    binding.CreateJointIndicesPrimvar(True, 1).Set([0])
    binding.CreateJointWeightsPrimvar(True, 1).Set([1.0])
    return quad


def test_blend_shapes_become_morph_targets_weighted_by_the_skel_animation(tmp_path):
    """UsdSkel: points + sum of weight_i x offsets_i, the weights the SkelAnimation's, found by
    name (the animation's order is not the mesh's). At 0.5 s (frame 12) the weights are half
    way, widen 0.25 and lift 0.5: corner 1 at (1.25, 0, 0), corner 2 at (1.25, 1, 1); at 1 s
    corner 2 at (1.5, 1, 2). glTF: POSITION + sum of w_k x target_k, w from the weights
    channel (LINEAR)."""
    stage = new_stage(tmp_path)
    _blend_shape_quad(stage)
    conversion, doc, blob = convert(stage, tmp_path)
    assert not [w for w in conversion.warnings if "blend" in w], conversion.warnings
    (node_index,) = [i for i, n in enumerate(doc["nodes"]) if n.get("name") == "Sheet"]
    mesh = doc["meshes"][doc["nodes"][node_index]["mesh"]]
    prim = mesh["primitives"][0]
    base = accessor(doc, blob, prim["attributes"]["POSITION"]).astype(np.float64)
    targets = [accessor(doc, blob, t["POSITION"]).astype(np.float64) for t in prim["targets"]]
    assert len(targets) == 2 and mesh["weights"] == [0.0, 0.0]  # at the start time
    times, weights = _morph_weights(doc, blob, node_index, 2)
    for seconds, expected in (
        (0.0, {(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)}),
        (0.5, {(0, 0, 0), (1.25, 0, 0), (1.25, 1, 1), (0, 1, 0)}),
        (1.0, {(0, 0, 0), (1.5, 0, 0), (1.5, 1, 2), (0, 1, 0)}),
    ):
        w = [np.interp(seconds, times, weights[:, k]) for k in range(2)]
        posed = base + sum(wk * t for wk, t in zip(w, targets, strict=True))
        assert {tuple(np.round(p, 6)) for p in posed} == expected, seconds


def test_in_between_blend_shapes_are_named_by_prim_path(tmp_path):
    stage = new_stage(tmp_path)
    _blend_shape_quad(stage, inbetween=True)
    conversion, doc, _ = convert(stage, tmp_path)
    assert any(w.startswith("/Rig/Sheet/Lift: in-between shapes are not converted")
               for w in conversion.warnings), conversion.warnings  # fmt: skip
    assert len(doc["meshes"][0]["primitives"][0]["targets"]) == 2  # still converted


def test_dual_quaternion_skinning_is_named_by_prim_path(tmp_path):
    """glTF skins blend matrices linearly; a mesh asking for dual-quaternion skinning is
    rendered so, with a warning naming it."""
    from pxr import UsdSkel

    stage = new_stage(tmp_path)
    quad = _blend_shape_quad(stage)
    UsdSkel.BindingAPI(quad.GetPrim()).CreateSkinningMethodAttr(UsdSkel.Tokens.dualQuaternion)
    conversion, doc, _ = convert(stage, tmp_path)
    assert any(w.startswith("/Rig/Sheet: dual-quaternion skinning is rendered as linear blend")
               for w in conversion.warnings), conversion.warnings  # fmt: skip
    assert "skins" in doc


def test_normals_that_change_with_the_points_become_normal_morph_targets(tmp_path):
    """A quad in the XY plane (normal +Z) turned to face +X by frame 24, its authored vertex
    normals turning with it: at 1 s the shading normal of every corner is +X, at 0.5 s half
    way (the normalized mean of +Z and +X), as USD interpolates the normals linearly. glTF:
    NORMAL + sum of w_k x NORMAL target_k, normalized."""
    stage = new_stage(tmp_path)
    stage.SetTimeCodesPerSecond(24.0)
    stage.SetStartTimeCode(0.0)
    quad = UsdGeom.Mesh.Define(stage, "/Card")
    quad.CreateFaceVertexCountsAttr([4])
    quad.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    quad.CreateSubdivisionSchemeAttr("none")
    points, normals = quad.CreatePointsAttr(), quad.CreateNormalsAttr()
    quad.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    points.Set([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)], 0.0)
    points.Set([(0, 0, 0), (0, 0, -1), (0, 1, -1), (0, 1, 0)], 24.0)
    normals.Set([(0, 0, 1)] * 4, 0.0)
    normals.Set([(1, 0, 0)] * 4, 24.0)
    conversion, doc, blob = convert(stage, tmp_path)
    assert not [w for w in conversion.warnings if "normal" in w], conversion.warnings
    (node_index,) = [i for i, n in enumerate(doc["nodes"]) if n.get("name") == "Card"]
    prim = doc["meshes"][doc["nodes"][node_index]["mesh"]]["primitives"][0]
    base = accessor(doc, blob, prim["attributes"]["NORMAL"]).astype(np.float64)
    targets = [accessor(doc, blob, t["NORMAL"]).astype(np.float64) for t in prim["targets"]]
    times, weights = _morph_weights(doc, blob, node_index, len(targets))
    half = np.array([1.0, 0.0, 1.0]) / math.sqrt(2)
    for seconds, expected in ((0.0, [0, 0, 1]), (0.5, half), (1.0, [1, 0, 0])):
        w = [np.interp(seconds, times, weights[:, k]) for k in range(len(targets))]
        n = base + sum(wk * t for wk, t in zip(w, targets, strict=True))
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        assert n == pytest.approx(np.tile(expected, (len(n), 1)), abs=1e-6), seconds


def test_normals_that_change_over_still_points_are_named_by_prim_path(tmp_path):
    stage = new_stage(tmp_path)
    mesh = unit_cube(stage, "/Cube")
    normals = mesh.CreateNormalsAttr()
    mesh.SetNormalsInterpolation(UsdGeom.Tokens.constant)
    normals.Set([(0, 0, 1)], 0.0)
    normals.Set([(1, 0, 0)], 24.0)
    conversion, _, _ = convert(stage, tmp_path)
    assert any(w.startswith("/Cube: normals that change over time on points that do not")
               for w in conversion.warnings), conversion.warnings  # fmt: skip


def test_a_diffuse_color_read_from_a_primvar_is_the_vertex_colour(tmp_path):
    """A UsdPreviewSurface whose diffuseColor is a UsdPrimvarReader_float3 of displayColor (as
    the USD Working Group's Teapot binds one material to differently coloured teapots): each
    mesh's own primvar as COLOR_0 with a base colour factor of 1 (glTF multiplies them), per
    point where the primvar varies, and the reader's fallback on a mesh without it."""
    stage = new_stage(tmp_path)
    material = _material(stage, "/Looks/Painted", roughness=0.4)
    reader = UsdShade.Shader.Define(stage, "/Looks/Painted/Colour")
    reader.CreateIdAttr("UsdPrimvarReader_float3")
    reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("displayColor")
    reader.CreateInput("fallback", Sdf.ValueTypeNames.Float3).Set(Gf.Vec3f(0.1, 0.2, 0.3))
    surface = UsdShade.Shader(stage.GetPrimAtPath("/Looks/Painted/Surface"))
    surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
        reader.ConnectableAPI(), "result"
    )
    plain = unit_cube(stage, "/Plain")
    plain.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant).Set([(0.9, 0.5, 0.1)])
    ramp = unit_cube(stage, "/Ramp")
    ramp.CreateDisplayColorPrimvar(UsdGeom.Tokens.vertex).Set(
        [(i / 7.0, 0.0, 1.0 - i / 7.0) for i in range(8)]
    )
    bare = unit_cube(stage, "/Bare")
    for mesh in (plain, ramp, bare):
        UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)
    conversion, doc, blob = convert(stage, tmp_path)
    assert not conversion.warnings, conversion.warnings

    def colours(name):
        (node,) = [n for n in doc["nodes"] if n.get("name") == name]
        prim = doc["meshes"][node["mesh"]]["primitives"][0]
        pbr = doc["materials"][prim["material"]]["pbrMetallicRoughness"]
        assert pbr["baseColorFactor"][:3] == [1.0, 1.0, 1.0]
        pos = accessor(doc, blob, prim["attributes"]["POSITION"]).astype(np.float64)
        col = accessor(doc, blob, prim["attributes"]["COLOR_0"]).astype(np.float64)
        return pos, col[:, :3]

    _, plain_col = colours("Plain")
    assert plain_col == pytest.approx(np.tile([0.9, 0.5, 0.1], (len(plain_col), 1)), abs=1e-6)
    _, bare_col = colours("Bare")
    assert bare_col == pytest.approx(np.tile([0.1, 0.2, 0.3], (len(bare_col), 1)), abs=1e-6)
    pos, ramp_col = colours("Ramp")
    for p, c in zip(pos, ramp_col, strict=True):
        # unit_cube's point i is (x, y, z) with x = i & 1, y = i >> 1 & 1, z = i >> 2 (+-0.5)
        i = int(p[0] > 0) + 2 * int(p[1] > 0) + 4 * int(p[2] > 0)
        assert c == pytest.approx([i / 7.0, 0.0, 1.0 - i / 7.0], abs=1e-6)


@pytest.mark.parametrize(
    ("scale", "bias", "expected"),
    [
        # glTF's own encoding: the file as it is.
        ((2, 2, 2, 1), (-1, -1, -1, 0), None),
        # A flipped green channel (DirectX): n = (2r - 1, 1 - 2g, 2b - 1).
        ((2, -2, 2, 1), (-1, 1, -1, 0), (0.5, 0.75, 1.0)),
        # x reversed, z unbiased: n = (1 - 2r, 2g - 1, b).
        ((-2, 2, 1, 1), (1, -1, 0, 0), (0.5, 0.25, 1.0)),
    ],
)
def test_a_normal_map_of_another_encoding_is_re_encoded_for_gltf(tmp_path, scale, bias, expected):
    """The USD Working Group's NormalsTextureBiasAndScale: three encodings of one normal map
    that should shade alike. USD's normal is texel x scale + bias; glTF's 2t' - 1, so the
    converter writes t' = (texel x scale + bias + 1) / 2. The texel (0.5, 0.25, 1) gives
    n = (0, 0.5, 1) with a flipped green, t' = (0.5, 0.75, 1); with x reversed and z
    unbiased n = (0, -0.5, 1), t' = (0.5, 0.25, 1)."""
    import OpenImageIO as oiio

    _png(tmp_path / "n.png", np.tile([0.5, 0.25, 1.0], (2, 2, 1)))
    stage = new_stage(tmp_path)
    mesh = unit_cube(stage, "/Cube")
    material = _material(stage, "/Looks/Bumpy")
    texture = UsdShade.Shader.Define(stage, "/Looks/Bumpy/Normal")
    texture.CreateIdAttr("UsdUVTexture")
    texture.CreateInput("file", Sdf.ValueTypeNames.Asset).Set("./n.png")
    texture.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("raw")
    texture.CreateInput("scale", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(*scale))
    texture.CreateInput("bias", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(*bias))
    surface = UsdShade.Shader(stage.GetPrimAtPath("/Looks/Bumpy/Surface"))
    surface.CreateInput("normal", Sdf.ValueTypeNames.Normal3f).ConnectToSource(
        texture.ConnectableAPI(), "rgb"
    )
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)
    conversion, doc, blob = convert(stage, tmp_path)
    assert not [w for w in conversion.warnings if "normal" in w], conversion.warnings
    normal = doc["materials"][0]["normalTexture"]
    image = doc["images"][doc["textures"][normal["index"]]["source"]]
    view = doc["bufferViews"][image["bufferView"]]
    data = blob[view["byteOffset"] : view["byteOffset"] + view["byteLength"]]
    if expected is None:
        assert data == (tmp_path / "n.png").read_bytes()
        return
    (tmp_path / "out.png").write_bytes(data)
    texels = np.asarray(oiio.ImageBuf(str(tmp_path / "out.png")).get_pixels(oiio.FLOAT))
    assert texels[..., :3] == pytest.approx(np.tile(expected, (2, 2, 1)), abs=1 / 255)


def test_a_textures_source_colour_space_is_honoured(tmp_path):
    """UsdUVTexture's sourceColorSpace says how the file's values are encoded: "raw" on a
    diffuse texture is read as it is, where glTF's baseColorTexture decodes sRGB, so the
    texel is sRGB-encoded for glTF (0.2 raw -> 0.4845); "sRGB" on a roughness texture is
    decoded, where glTF reads metallic-roughness linearly (0.8 -> 0.6038; the USD Working
    Group's RoughnessTest authors its roughness this way)."""
    import OpenImageIO as oiio

    _png(tmp_path / "colour.png", np.full((2, 2, 3), 0.2))
    _png(tmp_path / "rough.png", np.full((2, 2, 3), 0.8))
    stage = new_stage(tmp_path)
    mesh = unit_cube(stage, "/Cube")
    material = _material(stage, "/Looks/Flagged")
    surface = UsdShade.Shader(stage.GetPrimAtPath("/Looks/Flagged/Surface"))
    for name, file, space, output, kind in (
        ("diffuseColor", "colour.png", "raw", "rgb", Sdf.ValueTypeNames.Color3f),
        ("roughness", "rough.png", "sRGB", "g", Sdf.ValueTypeNames.Float),
    ):
        texture = UsdShade.Shader.Define(stage, f"/Looks/Flagged/{name}Tex")
        texture.CreateIdAttr("UsdUVTexture")
        texture.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(f"./{file}")
        texture.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set(space)
        surface.CreateInput(name, kind).ConnectToSource(texture.ConnectableAPI(), output)
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)
    _, doc, blob = convert(stage, tmp_path)
    pbr = doc["materials"][0]["pbrMetallicRoughness"]

    def texels(info):
        image = doc["images"][doc["textures"][info["index"]]["source"]]
        view = doc["bufferViews"][image["bufferView"]]
        (tmp_path / "out.png").write_bytes(
            blob[view["byteOffset"] : view["byteOffset"] + view["byteLength"]]
        )
        return np.asarray(oiio.ImageBuf(str(tmp_path / "out.png")).get_pixels(oiio.FLOAT))

    raw = round(0.2 * 255) / 255
    encoded = 1.055 * raw ** (1 / 2.4) - 0.055
    assert texels(pbr["baseColorTexture"])[..., :3] == pytest.approx(encoded, abs=1 / 255)
    srgb = round(0.8 * 255) / 255
    decoded = ((srgb + 0.055) / 1.055) ** 2.4
    assert texels(pbr["metallicRoughnessTexture"])[..., 1] == pytest.approx(decoded, abs=1 / 255)


# ------------------------------------------------------------------ intrinsic shapes


@pytest.mark.parametrize(
    ("kind", "axis", "attrs", "extent", "area"),
    [
        # Cylinder r = 0.5, h = 2 along X: side 2 pi r h, caps 2 pi r^2.
        ("Cylinder", "X", {"radius": 0.5, "height": 2.0}, [2.0, 1.0, 1.0],
         2 * math.pi * 0.5 * 2.0 + 2 * math.pi * 0.25),
        # Cone r = 1, h = 2 along Y: side pi r sqrt(r^2 + h^2), base pi r^2.
        ("Cone", "Y", {"radius": 1.0, "height": 2.0}, [2.0, 2.0, 2.0],
         math.pi * math.sqrt(5.0) + math.pi),
        # Capsule r = 0.5, spine 1 along Z: a sphere 4 pi r^2 and a tube 2 pi r h.
        ("Capsule", "Z", {"radius": 0.5, "height": 1.0}, [1.0, 1.0, 2.0],
         4 * math.pi * 0.25 + 2 * math.pi * 0.5),
        # Cylinder_1 from r 1 (bottom) to 0.5 (top), h 1 along Z: a frustum and two caps.
        ("Cylinder_1", "Z", {"radiusBottom": 1.0, "radiusTop": 0.5, "height": 1.0},
         [2.0, 2.0, 1.0], math.pi * 1.5 * math.hypot(0.5, 1.0) + math.pi * 1.25),
        # Plane 3 x 2 facing +X: width along z, length along y.
        ("Plane", "X", {"width": 3.0, "length": 2.0}, [0.0, 2.0, 3.0], 6.0),
    ],
)  # fmt: skip
def test_intrinsic_shapes_are_tessellated_as_usdgeom_defines_them(
    tmp_path, kind, axis, attrs, extent, area
):
    """Each shape's bounds (its extent along its axis, in metres from centimetres) and surface
    area, within the tessellation's error (48 facets around: the inscribed polygon's
    perimeter is 0.3 % short of the circle's), every triangle facing outward (from the
    centre; the plane along +axis)."""
    stage = new_stage(tmp_path, meters_per_unit=0.01)
    prim = stage.DefinePrim("/Shape", kind)
    prim.GetAttribute("axis").Set(axis)
    for name, value in attrs.items():
        prim.GetAttribute(name).Set(value * 100.0)  # centimetres
    conversion, doc, blob = convert(stage, tmp_path)
    assert not conversion.warnings, conversion.warnings
    triangles = np.array(world_triangles(doc, blob, "Shape"))
    points = triangles.reshape(-1, 3)
    assert points.max(axis=0) - points.min(axis=0) == pytest.approx(extent, rel=0.01, abs=1e-9)
    cross = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    assert np.linalg.norm(cross, axis=1).sum() / 2 == pytest.approx(area, rel=0.01)
    if kind == "Plane":
        assert (cross[:, 0] > 0).all()  # facing +X
    else:
        outward = (cross * (triangles.mean(axis=1) - points.mean(axis=0))).sum(axis=1)
        assert (outward > 0).all()


# ------------------------------------------------------------------ containment: clip templates,
# nested packages and the composed stage's layers

_CLIPPED = """#usda 1.0
(
    startTimeCode = 1
    endTimeCode = 1
)
def Mesh "Thing" (
    clips = {
        dictionary default = {
            string templateAssetPath = "TEMPLATE"
            double templateStartTime = START
            double templateEndTime = END
            double templateStride = STRIDE
            string primPath = "/Geo"
        }
    }
)
{
    uniform token subdivisionScheme = "none"
    int[] faceVertexCounts = [3]
    int[] faceVertexIndices = [0, 1, 2]
    point3f[] points
}
"""

_CLIP = """#usda 1.0
def Mesh "Geo"
{
    point3f[] points.timeSamples = { 1: [(0, 0, 0), (SIZE, 0, 0), (0, SIZE, 0)] }
}
"""


def _clipped(root: Path, template: str, start=1, end=1, stride=1) -> Path:
    text = _CLIPPED.replace("TEMPLATE", template).replace("STRIDE", str(stride))
    layer = root / "shot.usda"
    layer.write_text(text.replace("START", str(start)).replace("END", str(end)))
    return layer


@pytest.mark.parametrize("kind", ["dot-dot", "absolute"])
def test_a_value_clip_template_outside_the_upload_is_refused(tmp_path, kind):
    """clips.templateAssetPath names clip layers as assetPaths do: a template that leads out of
    the upload (USD would compose ../outside/clip.1.usda's points) is refused, naming it."""
    root = tmp_path / "upload"
    root.mkdir()
    (tmp_path / "outside").mkdir()
    (tmp_path / "outside" / "clip.1.usda").write_text(_CLIP.replace("SIZE", "7"))
    template = {
        "dot-dot": "../outside/clip.#.usda",
        "absolute": str(tmp_path / "outside" / "clip.#.usda"),
    }[kind]
    layer = _clipped(root, template)
    with pytest.raises(SceneError) as refused:
        convert_stage(layer, root, root)
    assert refused.value.field == "scene:/Thing.clips[default].templateAssetPath"
    assert ("'..'" if kind == "dot-dot" else "absolute") in refused.value.message


def test_a_value_clip_template_inside_the_upload_names_the_clips_usd_names(tmp_path):
    """USD's rule (UsdClipsAPI): the hash groups of the file name take the time's integer part,
    zero-padded to their width, and its fraction to as many digits: start 1, end 2, stride 0.5
    name clip.001.00, clip.001.50 and clip.002.00. Each clip layer is checked as any layer, and
    the clip's points (a triangle of legs 5 cm) are the mesh's."""
    root = tmp_path / "upload"
    (root / "clips").mkdir(parents=True)
    names = ["clips/clip.001.00.usda", "clips/clip.001.50.usda", "clips/clip.002.00.usda"]
    for name in names:
        (root / name).write_text(_CLIP.replace("SIZE", "5"))
    layer = _clipped(root, "clips/clip.###.##.usda", 1, 2, 0.5)
    stage = Usd.Stage.Open(str(layer))
    usd_says = [Path(a.resolvedPath) for a in Usd.ClipsAPI(stage.GetPrimAtPath("/Thing"))
                .ComputeClipAssetPaths("default")]  # fmt: skip
    assert usd_says == [root / n for n in names]
    from renderfarm.domain.scenes.usd_assets import template_clip_paths

    assert template_clip_paths("clips/clip.###.##.usda", 1.0, 2.0, 0.5) == names
    _, doc, blob = convert(stage, root)
    (tri,) = world_triangles(doc, blob, "Thing")
    assert sorted(map(tuple, np.round(tri, 6))) == [(0, 0, 0), (0, 0.05, 0), (0.05, 0, 0)]

    # A clip layer the template names is a layer of the stage: its asset paths are checked.
    other = tmp_path / "other"
    shutil.copytree(root, other)
    bad = 'def "X"\n{\n    asset a = @/etc/hostname@\n}\n'
    (other / names[1]).write_text(_CLIP.replace("SIZE", "5") + bad)
    with pytest.raises(SceneError) as refused:
        convert_stage(other / "shot.usda", other, other)
    assert refused.value.field == "scene:/X.a" and "absolute" in refused.value.message


def test_a_value_clip_template_over_too_many_times_is_refused(tmp_path):
    root = tmp_path / "upload"
    root.mkdir()
    layer = _clipped(root, "clip.#.usda", 0, 10_000_000, 1)
    with pytest.raises(SceneError) as refused:
        convert_stage(layer, root, root)
    assert refused.value.field == "scene:/Thing.clips[default].templateAssetPath"
    assert "clips" in refused.value.message


_ASSET = """#usda 1.0
(
    defaultPrim = "Asset"
)
def "Asset" (
    references = @./parts/sub.usda@</Part>
)
{
}
"""

_PART = """#usda 1.0
def "Part" (
    references = @REF@</Tri>
)
{
}
"""

_TRI = """#usda 1.0
def Mesh "Tri"
{
    uniform token subdivisionScheme = "none"
    int[] faceVertexCounts = [3]
    int[] faceVertexIndices = [0, 1, 2]
    point3f[] points = [(0, 0, 0), (SIZE, 0, 0), (0, SIZE, 0)]
    float2[] primvars:st = [(0, 0), (1, 0), (0, 1)] (
        interpolation = "vertex"
    )
    rel material:binding = </Tri/Looks/M>
    def Scope "Looks"
    {
        def Material "M"
        {
            token outputs:surface.connect = </Tri/Looks/M/Surface.outputs:surface>
            def Shader "Surface"
            {
                uniform token info:id = "UsdPreviewSurface"
                color3f inputs:diffuseColor.connect = </Tri/Looks/M/Tex.outputs:rgb>
                token outputs:surface
            }
            def Shader "Tex"
            {
                uniform token info:id = "UsdUVTexture"
                asset inputs:file = @../maps/wood.png@
                float3 outputs:rgb
            }
        }
    }
}
"""

_CARD = """#usda 1.0
def Mesh "Tri"
{
    uniform token subdivisionScheme = "none"
    int[] faceVertexCounts = [3]
    int[] faceVertexIndices = [0, 1, 2]
    point3f[] points = [(0, 0, 0), (SIZE, 0, 0), (0, SIZE, 0)]
}
"""

_SHOT = """#usda 1.0
def "Prop" (
    references = @./inner.usdz@
)
{
}
"""


def nested_package(tmp_path: Path, ref: str, size: int = 3) -> bytes:
    """inner.usdz: asset.usda (its root layer) -> parts/sub.usda -> `ref` (a triangle with a
    texture of the package, maps/wood.png, named from parts/tri.usda as ../maps/wood.png),
    written by usd-core's own package writer."""
    src = tmp_path / "package-src"
    (src / "parts").mkdir(parents=True)
    (src / "maps").mkdir()
    (src / "asset.usda").write_text(_ASSET)
    (src / "parts" / "sub.usda").write_text(_PART.replace("REF", ref))
    (src / "parts" / "tri.usda").write_text(_TRI.replace("SIZE", str(size)))
    _png(src / "maps" / "wood.png", np.full((2, 2, 3), 0.25))
    out = tmp_path / "inner.usdz"
    writer = Sdf.ZipFileWriter.CreateNew(str(out))
    for name in ("asset.usda", "parts/sub.usda", "parts/tri.usda", "maps/wood.png"):
        writer.AddFile(str(src / name), name)
    writer.Save()
    return out.read_bytes()


def test_a_multi_layer_package_inside_a_bundle_converts_from_its_own_files(tmp_path):
    """A bundle's layer referencing a .usdz whose root layer names parts/sub.usda inside the
    package (as USD anchors it: inner.usdz[parts/sub.usda]), which names parts/tri.usda, whose
    texture is maps/wood.png in the package: all read from the package, nothing beside it."""
    root = tmp_path / "upload"
    root.mkdir()
    data = nested_package(tmp_path, "./tri.usda")
    (root / "inner.usdz").write_bytes(data)
    (root / "shot.usda").write_text(_SHOT)
    conversion = convert_stage(root / "shot.usda", root, tmp_path)
    doc, blob = read_glb(conversion.glb)
    (tri,) = world_triangles(doc, blob, "Prop")
    assert sorted(map(tuple, np.round(tri, 6))) == [(0, 0, 0), (0, 0.03, 0), (0.03, 0, 0)]
    (image,) = doc["images"]
    view = doc["bufferViews"][image["bufferView"]]
    png = (tmp_path / "package-src" / "maps" / "wood.png").read_bytes()
    assert blob[view["byteOffset"] : view["byteOffset"] + view["byteLength"]] == png


@pytest.mark.parametrize("ref", ["absolute", "../../outside.usda", "./missing.usda"])
def test_a_layer_inside_a_nested_package_is_checked_inside_the_package(tmp_path, ref):
    """The package's layers are checked where USD reads them, inside the package: an absolute
    path there (which USD would compose), a path climbing out of the package, or one naming no
    file of the package is refused, even with a same-named loose file beside the package."""
    root = tmp_path / "upload"
    (root / "parts").mkdir(parents=True)
    (tmp_path / "outside.usda").write_text(_CARD.replace("SIZE", "9"))
    written = str(tmp_path / "outside.usda") if ref == "absolute" else ref
    (root / "inner.usdz").write_bytes(nested_package(tmp_path, written))
    (root / "shot.usda").write_text(_SHOT)
    (root / "parts" / "sub.usda").write_text(_PART.replace("REF", "./tri.usda"))  # decoys
    (root / "parts" / "tri.usda").write_text(_TRI.replace("SIZE", "1"))
    (root / "missing.usda").write_text(_TRI.replace("SIZE", "1"))
    (root / "outside.usda").write_text(_TRI.replace("SIZE", "1"))
    (root / "maps").mkdir()
    _png(root / "maps" / "wood.png", np.full((2, 2, 3), 0.5))
    with pytest.raises(SceneError) as refused:
        convert_stage(root / "shot.usda", root, tmp_path)
    assert refused.value.field == "scene:/Part.references"
    assert "inner.usdz[parts/sub.usda]" in refused.value.message
    words = {"absolute": "absolute", "./missing.usda": "names no file of the package"}
    assert words.get(ref, "climbs out of the package") in refused.value.message


def test_a_composed_layer_outside_the_upload_is_refused_after_composition(tmp_path):
    """The defence behind the checks: a stage whose composition used a layer outside the upload
    (composed here without the checks) is refused, naming the layer."""
    from renderfarm.domain.scenes.usd_assets import check_used_layers

    root = tmp_path / "upload"
    root.mkdir()
    (tmp_path / "outside.usda").write_text(_CARD.replace("SIZE", "9"))
    (root / "shot.usda").write_text(_PART.replace("REF", str(tmp_path / "outside.usda")))
    stage = Usd.Stage.Open(str(root / "shot.usda"))
    with pytest.raises(SceneError) as refused:
        check_used_layers(stage, root)
    assert str(tmp_path / "outside.usda") in refused.value.message
    check_used_layers(Usd.Stage.Open(str(root / "shot.usda")), tmp_path)  # inside: no error


# ------------------------------------------------------------------ displayOpacity and warnings


def test_display_opacity_is_the_base_colours_alpha(tmp_path):
    """UsdGeomGprim: displayOpacity is the companion of displayColor, the opacity the viewport
    draws a prim with no material; glTF carries opacity as the base colour's alpha, which only
    alphaMode BLEND applies (OPAQUE ignores it). Constant: baseColorFactor (0.2, 0.4, 0.6, 0.25);
    per vertex: COLOR_0's alpha at each corner the vertex's opacity, the factor's alpha 1."""
    stage = new_stage(tmp_path)
    flat = unit_cube(stage, "/Flat")
    flat.CreateDisplayColorAttr([(0.2, 0.4, 0.6)])
    flat.CreateDisplayOpacityAttr([0.25])
    varying = unit_cube(stage, "/Varying")
    opacities = [0.0, 0.125, 0.25, 0.375, 0.5, 0.625, 0.75, 0.875]  # one per corner point
    varying.CreateDisplayOpacityPrimvar(UsdGeom.Tokens.vertex).Set(opacities)
    _, doc, blob = convert(stage, tmp_path)
    meshes = {n["name"]: doc["meshes"][n["mesh"]] for n in doc["nodes"] if "mesh" in n}
    (prim,) = meshes["Flat"]["primitives"]
    material = doc["materials"][prim["material"]]
    assert material["pbrMetallicRoughness"]["baseColorFactor"] == pytest.approx(
        [0.2, 0.4, 0.6, 0.25], abs=1e-6
    )
    assert material["alphaMode"] == "BLEND"
    (prim,) = meshes["Varying"]["primitives"]
    material = doc["materials"][prim["material"]]
    assert material["alphaMode"] == "BLEND"
    assert material["pbrMetallicRoughness"].get("baseColorFactor", [1, 1, 1, 1])[3] == 1.0
    pos = accessor(doc, blob, prim["attributes"]["POSITION"]).astype(np.float64)
    colour = accessor(doc, blob, prim["attributes"]["COLOR_0"]).astype(np.float64)
    kind = doc["accessors"][prim["attributes"]["COLOR_0"]]["componentType"]
    colour /= {5126: 1.0, 5121: 255.0, 5123: 65535.0}[kind]  # glTF: normalized integers
    assert colour.shape[1] == 4
    # The cube's points in unit_cube's order: x fastest, then y, then z, each -0.5 or 0.5.
    index = (pos[:, 0] > 0) * 1 + (pos[:, 1] > 0) * 2 + (pos[:, 2] > 0) * 4
    assert colour[:, 3] == pytest.approx(np.array(opacities)[index], abs=1 / 255)


def test_an_mdl_surface_is_one_warning_and_the_default_material(tmp_path):
    """An Omniverse material: outputs:mdl:surface from a shader whose module, OmniPBR.mdl,
    comes from the renderer's search path (not uploaded, never read): one warning naming the
    material, and the cube gets the default material (0.18 grey)."""
    stage = new_stage(tmp_path)
    cube = unit_cube(stage, "/Cube")
    material = UsdShade.Material.Define(stage, "/Looks/Omni")
    shader = UsdShade.Shader.Define(stage, "/Looks/Omni/Shader")
    shader.SetSourceAsset(Sdf.AssetPath("OmniPBR.mdl"), "mdl")
    shader.SetSourceAssetSubIdentifier("OmniPBR", "mdl")
    material.CreateSurfaceOutput("mdl").ConnectToSource(shader.ConnectableAPI(), "out")
    UsdShade.MaterialBindingAPI.Apply(cube.GetPrim()).Bind(material)
    conversion, doc, _ = convert(stage, tmp_path)
    mine = [w for w in conversion.warnings if w.startswith("/Looks/Omni:")]
    assert len(mine) == 1 and "MDL" in mine[0], conversion.warnings
    (node,) = [n for n in doc["nodes"] if n.get("name") == "Cube"]
    (prim,) = doc["meshes"][node["mesh"]]["primitives"]
    base = doc["materials"][prim["material"]]["pbrMetallicRoughness"]["baseColorFactor"]
    assert base[:3] == pytest.approx([0.18, 0.18, 0.18], abs=1e-6)


def test_a_volume_is_one_warning_by_prim_path(tmp_path):
    from pxr import UsdVol

    stage = new_stage(tmp_path)
    unit_cube(stage, "/Cube")
    (tmp_path / "smoke.vdb").write_bytes(b"")  # named, never read
    volume = UsdVol.Volume.Define(stage, "/Smoke")
    field = UsdVol.OpenVDBAsset.Define(stage, "/Smoke/density")
    field.CreateFilePathAttr(Sdf.AssetPath("smoke.vdb"))
    field.CreateFieldNameAttr("density")
    volume.CreateFieldRelationship("density", field.GetPath())
    conversion, doc, _ = convert(stage, tmp_path)
    mine = [w for w in conversion.warnings if w.startswith("/Smoke:")]
    assert len(mine) == 1 and "not converted" in mine[0], conversion.warnings
    assert not any(n.get("name") == "Smoke" and "mesh" in n for n in doc["nodes"])


@pytest.mark.parametrize("collection", ["lightLink", "shadowLink"])
@pytest.mark.parametrize("how", ["includes", "excludes", "includeRoot false"])
def test_light_and_shadow_linking_are_one_warning_each(tmp_path, collection, how):
    """UsdLuxLightAPI's collections: a link that names prims to include or exclude, or whose
    includeRoot is false (then the light reaches its includes alone), is not carried: one
    warning on the light's path. A collection authored to include everything is no warning."""
    stage = new_stage(tmp_path)
    unit_cube(stage, "/Cube")
    light = UsdLux.SphereLight.Define(stage, "/Light")
    plain = UsdLux.SphereLight.Define(stage, "/Plain")
    api = UsdLux.LightAPI(light)
    link = (
        api.GetLightLinkCollectionAPI()
        if collection == "lightLink"
        else api.GetShadowLinkCollectionAPI()
    )
    if how == "includes":
        link.CreateIncludeRootAttr(False)
        link.CreateIncludesRel().AddTarget("/Cube")
    elif how == "excludes":
        link.CreateExcludesRel().AddTarget("/Cube")
    else:
        link.CreateIncludeRootAttr(False)
    UsdLux.LightAPI(plain).GetLightLinkCollectionAPI().CreateIncludeRootAttr(True)
    UsdLux.LightAPI(plain).GetShadowLinkCollectionAPI().CreateIncludeRootAttr(True)
    conversion, _, _ = convert(stage, tmp_path)
    mine = [w for w in conversion.warnings if w.startswith("/Light:")]
    word = "light linking" if collection == "lightLink" else "shadow linking"
    assert len(mine) == 1 and word in mine[0], conversion.warnings
    assert not [w for w in conversion.warnings if w.startswith("/Plain:")]


@pytest.mark.parametrize("separator", ["/", "\\"])
def test_a_dot_dot_path_that_stays_inside_the_upload_is_read(tmp_path, separator):
    """Packaged assets name files of a sibling folder from a layer in a subfolder
    (layers/look.usda: ../maps/colour.png, as the USD Working Group's Standard Shader Ball
    does): a '..' that stays inside the upload is allowed, and the texture is read. Written
    with '\\' (..\\maps\\colour.png, as exporters on Windows write it), USD's resolver on
    Linux finds no such file, so the path is read with '\\' as '/' from the authoring layer's
    folder, checked as any asset path, and embedded; one climbing out of the upload either way
    is refused as any '..' is."""
    root = tmp_path / "upload"
    (root / "maps").mkdir(parents=True)
    (root / "layers").mkdir()
    _png(root / "maps" / "colour.png", np.full((2, 2, 3), 0.5))
    png = (root / "maps" / "colour.png").read_bytes()
    look = Usd.Stage.CreateNew(str(root / "layers" / "look.usda"))
    _textured(look, separator.join(["..", "maps", "colour.png"]))
    look.GetRootLayer().Save()
    stage = new_stage(root)
    stage.GetRootLayer().subLayerPaths.append("./layers/look.usda")
    _, doc, blob = convert(stage, root)
    (image,) = doc["images"]
    view = doc["bufferViews"][image["bufferView"]]
    assert blob[view["byteOffset"] : view["byteOffset"] + view["byteLength"]] == png

    other = tmp_path / "other"
    other.mkdir()
    escaping = new_stage(other)
    _textured(escaping, separator.join(["..", "upload", "maps", "colour.png"]))
    with pytest.raises(SceneError) as refused:
        convert(escaping, other)
    assert refused.value.field == "scene:/World/Looks/M/Tex.inputs:file"
    assert "'..'" in refused.value.message
