#!/usr/bin/env python3
"""Write an example OpenUSD scene, usd-still-life.usdz: what a studio pipeline hands on, for the
farm's USD import (docs/scenes.md, "USD scenes").

A Z-up stage in centimetres (metersPerUnit 0.01) holding: a floor mesh with a checker texture
read through a UsdPrimvarReader_float2 and a UsdTransform2d (tiled 4 x 4); a two-coloured block
whose faces are split between two materials by UsdGeomSubsets; a row of clear-coated balls
placed by a PointInstancer (one shared sphere); three instanceable references to one crate
asset (one shared mesh); a gold block in UsdPreviewSurface's specular workflow; a camera with
focal length, apertures and depth of field; a rect light (an emissive panel), a sun (a distant
light) and a pale sky (a dome light: the job's environment).

Usage:
    python make_usd_scene.py                      # write usd-still-life.usdz next to this script
    python make_usd_scene.py -o OUT.usdz          # elsewhere (.usdz, or .usda for the loose files)
    renderfarm render examples/usd-still-life.usdz -o out/usd.exr --width 480 --height 320

Needs usd-core (`pip install usd-core`, a dependency of the server package).
"""

from __future__ import annotations

import argparse
import struct
import tempfile
import zlib
from pathlib import Path


def checker_png(size: int = 64, cells: int = 8) -> bytes:
    """An sRGB checker of two warm greys as a PNG (standard library only)."""
    rows = []
    for y in range(size):
        row = bytearray([0])  # filter type 0 for each scanline
        for x in range(size):
            dark = ((x * cells // size) + (y * cells // size)) % 2
            row += bytes((90, 80, 70) if dark else (200, 190, 170))
        rows.append(bytes(row))

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
        )

    header = struct.pack(">IIBBBBB", size, size, 8, 2, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(b"".join(rows)))
        + chunk(b"IEND", b"")
    )


def preview_material(stage, path: str, **inputs):
    from pxr import Sdf, UsdShade

    material = UsdShade.Material.Define(stage, path)
    shader = UsdShade.Shader.Define(stage, f"{path}/Surface")
    shader.CreateIdAttr("UsdPreviewSurface")
    for name, value in inputs.items():
        if isinstance(value, tuple):
            kind = Sdf.ValueTypeNames.Color3f
        elif isinstance(value, int) and not isinstance(value, bool):
            kind = Sdf.ValueTypeNames.Int
        else:
            kind = Sdf.ValueTypeNames.Float
        shader.CreateInput(name, kind).Set(value)
    material.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
    return material, shader


def box_mesh(stage, path: str, half: tuple[float, float, float]):
    from pxr import UsdGeom

    hx, hy, hz = half
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr(
        [(x * hx, y * hy, z * hz) for z in (-1, 1) for y in (-1, 1) for x in (-1, 1)]
    )
    mesh.CreateFaceVertexCountsAttr([4] * 6)
    # bottom, top, front (-Y), back (+Y), left (-X), right (+X); counter-clockwise outside
    mesh.CreateFaceVertexIndicesAttr(
        [0, 2, 3, 1, 4, 5, 7, 6, 0, 1, 5, 4, 2, 6, 7, 3, 0, 4, 6, 2, 1, 3, 7, 5]
    )
    mesh.CreateSubdivisionSchemeAttr("none")
    return mesh


def build(directory: Path) -> Path:
    """Write scene.usda and textures/checker.png into `directory`; return the layer's path."""
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdShade

    (directory / "textures").mkdir(parents=True, exist_ok=True)
    (directory / "textures" / "checker.png").write_bytes(checker_png())
    layer = directory / "scene.usda"
    stage = Usd.Stage.CreateNew(str(layer))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())

    # Floor: 4 m square, checker tiled 4 x 4 by a UsdTransform2d.
    floor = UsdGeom.Mesh.Define(stage, "/World/Floor")
    floor.CreatePointsAttr([(-200, -200, 0), (200, -200, 0), (200, 200, 0), (-200, 200, 0)])
    floor.CreateFaceVertexCountsAttr([4])
    floor.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    floor.CreateSubdivisionSchemeAttr("none")
    floor.CreateNormalsAttr([(0, 0, 1)] * 4)
    floor.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    st = UsdGeom.PrimvarsAPI(floor).CreatePrimvar(
        "st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex
    )
    st.Set([(0, 0), (1, 0), (1, 1), (0, 1)])
    floor_material, floor_surface = preview_material(stage, "/World/Looks/Floor", roughness=0.8)
    reader = UsdShade.Shader.Define(stage, "/World/Looks/Floor/StReader")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.Token).Set("st")
    tiling = UsdShade.Shader.Define(stage, "/World/Looks/Floor/Tiling")
    tiling.CreateIdAttr("UsdTransform2d")
    tiling.CreateInput("in", Sdf.ValueTypeNames.Float2).ConnectToSource(
        reader.ConnectableAPI(), "result"
    )
    tiling.CreateInput("scale", Sdf.ValueTypeNames.Float2).Set(Gf.Vec2f(4, 4))
    texture = UsdShade.Shader.Define(stage, "/World/Looks/Floor/Checker")
    texture.CreateIdAttr("UsdUVTexture")
    texture.CreateInput("file", Sdf.ValueTypeNames.Asset).Set("./textures/checker.png")
    texture.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(
        tiling.ConnectableAPI(), "result"
    )
    texture.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set("repeat")
    texture.CreateInput("wrapT", Sdf.ValueTypeNames.Token).Set("repeat")
    texture.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
    floor_surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
        texture.ConnectableAPI(), "rgb"
    )
    UsdShade.MaterialBindingAPI.Apply(floor.GetPrim()).Bind(floor_material)

    # A block whose top and bottom are red, its sides blue: two GeomSubsets.
    block = box_mesh(stage, "/World/Block", (25, 25, 25))
    block.AddTranslateOp().Set(Gf.Vec3d(-60, 20, 25))
    block.AddRotateZOp().Set(30.0)
    red, _ = preview_material(stage, "/World/Looks/Red", diffuseColor=(0.7, 0.08, 0.05))
    blue, _ = preview_material(stage, "/World/Looks/Blue", diffuseColor=(0.05, 0.15, 0.6))
    binding = UsdShade.MaterialBindingAPI.Apply(block.GetPrim())
    for name, faces, material in (("caps", [0, 1], red), ("sides", [2, 3, 4, 5], blue)):
        subset = binding.CreateMaterialBindSubset(name, faces)
        UsdShade.MaterialBindingAPI.Apply(subset.GetPrim()).Bind(material)

    # Gold in the specular workflow.
    gold_block = box_mesh(stage, "/World/GoldBar", (20, 8, 6))
    gold_block.AddTranslateOp().Set(Gf.Vec3d(60, 40, 6))
    gold, _ = preview_material(
        stage, "/World/Looks/Gold", useSpecularWorkflow=1, specularColor=(1.0, 0.78, 0.34),
        roughness=0.3,
    )  # fmt: skip
    UsdShade.MaterialBindingAPI.Apply(gold_block.GetPrim()).Bind(gold)

    # A row of clear-coated balls: one sphere, five PointInstancer instances.
    instancer = UsdGeom.PointInstancer.Define(stage, "/World/Balls")
    ball = UsdGeom.Sphere.Define(stage, "/World/Balls/Prototypes/Ball")
    ball.CreateRadiusAttr(10.0)
    lacquer, _ = preview_material(
        stage, "/World/Looks/Lacquer", diffuseColor=(0.1, 0.5, 0.2), roughness=0.5,
        clearcoat=1.0, clearcoatRoughness=0.05,
    )  # fmt: skip
    UsdShade.MaterialBindingAPI.Apply(ball.GetPrim()).Bind(lacquer)
    instancer.CreatePrototypesRel().SetTargets([ball.GetPath()])
    instancer.CreateProtoIndicesAttr([0] * 5)
    instancer.CreatePositionsAttr([(-80 + 40 * i, -60, 10) for i in range(5)])

    # Three instanceable references to one crate.
    box_mesh(stage, "/Assets/Crate/Body", (10, 10, 10))
    crate_material, _ = preview_material(
        stage, "/Assets/Crate/Wood", diffuseColor=(0.55, 0.4, 0.25), roughness=0.7
    )
    UsdShade.MaterialBindingAPI.Apply(stage.GetPrimAtPath("/Assets/Crate/Body")).Bind(
        crate_material
    )
    stage.GetPrimAtPath("/Assets").SetSpecifier(Sdf.SpecifierClass)
    for i in range(3):
        crate = UsdGeom.Xform.Define(stage, f"/World/Crate{i}")
        crate.GetPrim().GetReferences().AddInternalReference("/Assets/Crate")
        crate.GetPrim().SetInstanceable(True)
        crate.AddTranslateOp().Set(Gf.Vec3d(100, -20 + 25 * i, 10))

    # Camera: 35 mm lens on a 36 x 24 mm back, 3 m from the scene, f/8 focused there.
    camera = UsdGeom.Camera.Define(stage, "/World/Camera")
    camera.CreateFocalLengthAttr(35.0)
    camera.CreateHorizontalApertureAttr(36.0)
    camera.CreateVerticalApertureAttr(24.0)
    camera.CreateClippingRangeAttr(Gf.Vec2f(1.0, 10000.0))
    camera.CreateFStopAttr(8.0)
    camera.CreateFocusDistanceAttr(320.0)
    camera.AddTranslateOp().Set(Gf.Vec3d(0, -300, 110))
    camera.AddRotateXOp().Set(72.0)  # the camera's -Z turned to look along +Y, tilted down

    # Lights: a 1 m x 0.5 m panel above, facing down, and a low sun.
    panel = UsdLux.RectLight.Define(stage, "/World/Lights/Panel")
    panel.CreateWidthAttr(100.0)
    panel.CreateHeightAttr(50.0)
    panel.CreateIntensityAttr(12.0)
    panel.CreateExposureAttr(1.0)
    panel.CreateColorAttr(Gf.Vec3f(1.0, 0.95, 0.85))
    panel.AddTranslateOp().Set(Gf.Vec3d(0, 0, 250))  # a RectLight emits along its -Z: down
    sun = UsdLux.DistantLight.Define(stage, "/World/Lights/Sun")
    sun.CreateIntensityAttr(3.0)
    sun.CreateNormalizeAttr(True)  # intensity is then the illuminance (lux)
    sun.AddRotateXYZOp().Set(Gf.Vec3f(50.0, 0.0, 35.0))
    # A pale sky: a dome light without a texture (the job's environment, a constant map). The
    # DomeLight_1 schema's pole follows the stage's up axis (Z here).
    sky = UsdLux.DomeLight_1.Define(stage, "/World/Lights/Sky")
    sky.CreateColorAttr(Gf.Vec3f(0.6, 0.75, 1.0))
    sky.CreateIntensityAttr(0.25)
    stage.GetRootLayer().Save()
    return layer


def write(out: Path) -> Path:
    """Write the scene as OUT (.usdz: one package; .usda: the layer and its textures/)."""
    from pxr import UsdUtils

    if out.suffix.lower() == ".usda":
        layer = build(out.parent)
        if layer != out:
            layer.rename(out)
        return out
    with tempfile.TemporaryDirectory() as tmp:
        layer = build(Path(tmp))
        if not UsdUtils.CreateNewUsdzPackage(str(layer), str(out)):
            raise SystemExit(f"could not write {out}")
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "-o", "--output", type=Path, default=Path(__file__).with_name("usd-still-life.usdz")
    )
    args = parser.parse_args()
    print(write(args.output))


if __name__ == "__main__":
    main()
