"""Light probes for bench/usd_parity.py --probes: USD stages whose image is a known function of
one light, so that a difference in light is found apart from materials and geometry.

Each stage is a 10 x 10 m Lambertian floor (UsdPreviewSurface: diffuseColor 0.8, specular
workflow with specularColor 0, roughness 1) seen from 1 m above, lit by one light 2 m above
it facing down (behind the camera: it is never seen directly), in metres unless named _cm:
the floor's radiance is 0.8 E / pi for the irradiance E the light gives, which UsdLux defines
from intensity, exposure, normalize, the light's size and its scale (docs/scenes.md, "USD
scenes"). Written with usd-core (the farm's venv):

    write_probes(folder) -> [paths]
"""

from __future__ import annotations

from pathlib import Path

# name: (light type, normalize, metersPerUnit, scale, {attribute: value})
PROBES: dict[str, tuple[str, bool, float, float, dict]] = {
    "probe_sphere": ("SphereLight", False, 1.0, 1.0, {"intensity": 10.0}),
    "probe_sphere_normalized": ("SphereLight", True, 1.0, 1.0, {"intensity": 10.0}),
    "probe_sphere_cm": ("SphereLight", False, 0.01, 1.0, {"intensity": 10.0}),
    "probe_rect": ("RectLight", False, 1.0, 1.0, {"intensity": 10.0}),
    "probe_rect_normalized": ("RectLight", True, 1.0, 1.0, {"intensity": 10.0}),
    "probe_rect_scaled": ("RectLight", False, 1.0, 2.0, {"intensity": 10.0}),
    "probe_disk_exposure": ("DiskLight", False, 1.0, 1.0, {"intensity": 10.0, "exposure": 1.0}),
    "probe_distant": ("DistantLight", False, 1.0, 1.0, {"intensity": 1000.0}),
    "probe_distant_normalized": ("DistantLight", True, 1.0, 1.0, {"intensity": 3.0}),
}


def write_probe(path: Path, kind: str, normalize: bool, mpu: float, scale: float, inputs: dict):
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdShade

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, mpu)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    unit = 1.0 / mpu  # one metre in scene units
    floor = UsdGeom.Mesh.Define(stage, "/Floor")
    h = 5.0 * unit
    floor.CreatePointsAttr([(-h, 0, h), (h, 0, h), (h, 0, -h), (-h, 0, -h)])
    floor.CreateFaceVertexCountsAttr([4])
    floor.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    floor.CreateSubdivisionSchemeAttr("none")
    material = UsdShade.Material.Define(stage, "/Looks/Lambert")
    shader = UsdShade.Shader.Define(stage, "/Looks/Lambert/Surface")
    shader.CreateIdAttr("UsdPreviewSurface")
    shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(0.8, 0.8, 0.8))
    shader.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(1.0)
    shader.CreateInput("useSpecularWorkflow", Sdf.ValueTypeNames.Int).Set(1)
    shader.CreateInput("specularColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(0, 0, 0))
    material.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
    UsdShade.MaterialBindingAPI.Apply(floor.GetPrim()).Bind(material)
    camera = UsdGeom.Camera.Define(stage, "/Camera")
    camera.CreateFocalLengthAttr(35.0)
    camera.CreateHorizontalApertureAttr(36.0)
    camera.CreateVerticalApertureAttr(24.0)
    camera.CreateClippingRangeAttr(Gf.Vec2f(0.01 * unit, 100.0 * unit))
    camera.AddTranslateOp().Set(Gf.Vec3d(0, 1.0 * unit, 0))
    camera.AddRotateXOp().Set(-90.0)  # looking down
    light = getattr(UsdLux, kind).Define(stage, "/Light")
    if kind == "SphereLight":
        light.CreateRadiusAttr(0.1 * unit)
    elif kind == "RectLight":
        light.CreateWidthAttr(0.5 * unit)
        light.CreateHeightAttr(0.5 * unit)
    elif kind == "DiskLight":
        light.CreateRadiusAttr(0.25 * unit)
    light.CreateNormalizeAttr(normalize)
    light.CreateIntensityAttr(inputs["intensity"])
    if "exposure" in inputs:
        light.CreateExposureAttr(inputs["exposure"])
    light.AddTranslateOp().Set(Gf.Vec3d(0, 2.0 * unit, 0))
    light.AddRotateXOp().Set(-90.0)  # -Z, where rect and disk lights emit, turned down
    if scale != 1.0:
        light.AddScaleOp().Set(Gf.Vec3f(scale, scale, scale))
    stage.GetRootLayer().Save()


def write_probes(folder: Path) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, (kind, normalize, mpu, scale, inputs) in PROBES.items():
        path = folder / f"{name}.usda"
        path.unlink(missing_ok=True)
        write_probe(path, kind, normalize, mpu, scale, inputs)
        paths.append(path)
    return paths
