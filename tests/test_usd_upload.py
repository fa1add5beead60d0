"""USD scenes submitted as users submit them (issue #41): a bundle of a .usda and its texture
over REST, a .usdz over gRPC and through the Python client (the CLI's path), each converted by
the server in its limited child process, accepted by the workers' loader and rendered; and a
stage naming a file outside the upload refused with 400 naming the prim and attribute, over
both APIs, before anything is read. Conversions whose glTF only the worker can judge (a spot
light) go through the acceptance path (`renderfarm-worker inspect`) and are rendered by
`renderfarm-worker render`, against analytic images.

The scene is the example generator's (examples/make_usd_scene.py). What the conversion must
produce is checked analytically in server/tests/test_usd_convert.py; here the path a user takes.
"""

from __future__ import annotations

import hashlib
import importlib.util
import io
import json
import math
import subprocess
import zipfile
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest

pytest.importorskip("pxr")

from renderfarm.domain.scenes.usd_convert import convert_stage  # noqa: E402
from renderfarm.infra.images import read_exr  # noqa: E402

from .apihelpers import TINY, Apis, Error  # noqa: E402
from .waiting import wait_until  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
GENERATOR = ROOT / "examples" / "make_usd_scene.py"
SETTINGS = {**TINY, "width": 48, "height": 32}

ESCAPING_LAYER = """#usda 1.0
(
    upAxis = "Y"
)

def Xform "World"
{
    def Mesh "Card" (
        prepend apiSchemas = ["MaterialBindingAPI"]
    )
    {
        int[] faceVertexCounts = [4]
        int[] faceVertexIndices = [0, 1, 2, 3]
        point3f[] points = [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)]
        rel material:binding = </World/Looks/M>
    }

    def Scope "Looks"
    {
        def Material "M"
        {
            token outputs:surface.connect = </World/Looks/M/Surface.outputs:surface>

            def Shader "Surface"
            {
                uniform token info:id = "UsdPreviewSurface"
                color3f inputs:diffuseColor.connect = </World/Looks/M/Tex.outputs:rgb>
                token outputs:surface
            }

            def Shader "Tex"
            {
                uniform token info:id = "UsdUVTexture"
                asset inputs:file = @PATH@
                float3 outputs:rgb
            }
        }
    }
}
"""


def load_generator():
    spec = importlib.util.spec_from_file_location("make_usd_scene", GENERATOR)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def apis(farm):
    a = Apis(farm.url, farm.grpc_address)
    wait_until(lambda: len(a.client.workers()) >= 1, 60, "a worker connected")
    yield a
    a.close()


@pytest.fixture(scope="module")
def usd_scene(tmp_path_factory) -> dict[str, Path]:
    """The example as loose files zipped (layer + textures/) and as a .usdz package."""
    generator = load_generator()
    loose = tmp_path_factory.mktemp("usd-loose")
    layer = generator.build(loose)
    bundle = loose.parent / "still-life.zip"
    with zipfile.ZipFile(bundle, "w") as archive:
        for path in sorted(loose.rglob("*")):
            if path.is_file():
                archive.write(path, path.relative_to(loose).as_posix())
    package = generator.write(tmp_path_factory.mktemp("usdz") / "still-life.usdz")
    return {"layer": layer, "bundle": bundle, "usdz": package}


def _finished(apis: Apis, job: dict) -> dict:
    job = apis.client.wait(job["id"], poll_s=0.2, timeout_s=300)
    assert job["state"] == "completed", job["error"]
    return job


def test_a_usd_bundle_over_rest_renders_and_the_job_names_its_source(apis, usd_scene, tmp_path):
    data = usd_scene["bundle"].read_bytes()
    job = apis.submit_rest(data, "still-life.zip", SETTINGS, "")
    assert not isinstance(job, Error), job
    assert job["name"] == "still-life.zip"
    # The camera's f/8 on a 35 mm lens: aperture radius 35 mm / 16; focused at 320 cm.
    assert job["settings"]["aperture_radius"] == pytest.approx(0.035 / 16, rel=1e-6)
    assert job["settings"]["focus_distance"] == pytest.approx(3.2, rel=1e-6)
    # The dome light is the job's environment: a stored map, scaled by its intensity.
    assert len(job["settings"]["environment"]) == 64
    assert job["settings"]["environment_intensity"] == pytest.approx(0.25, rel=1e-6)
    stored = apis.client.scene(job["scene_sha256"])
    assert stored["format"] == "glb" and stored["filename"] == "still-life.glb"
    job = _finished(apis, job)
    events = wait_until(
        lambda: [e for e in apis.client.events(job["id"]) if e["kind"] == "scene_converted"],
        30,
        "the scene_converted event",
    )
    (event,) = events
    assert event["data"]["source_sha256"] == hashlib.sha256(data).hexdigest()
    assert event["data"]["source_filename"] == "still-life.zip"
    # The sun's angle has a warning of its own.
    assert any(w.startswith("/World/Lights/Sun:") for w in event["data"]["warnings"])
    exr = tmp_path / "usd.exr"
    exr.write_bytes(apis.client.image(job["id"], "exr"))
    spec = oiio.ImageInput.open(str(exr)).spec()
    assert spec.getattribute("renderfarm:scene_source_sha256") == hashlib.sha256(data).hexdigest()
    assert spec.getattribute("renderfarm:scene_source_filename") == "still-life.zip"
    assert spec.getattribute("renderfarm:scene_source_format") == "usd"
    channels = read_exr(str(exr))
    rgb = np.stack([channels[c] for c in ("R", "G", "B")], axis=-1)
    assert np.isfinite(rgb).all() and rgb.mean() > 0.01  # lit, not black


def test_a_usdz_over_grpc_and_through_the_python_client_is_accepted(apis, usd_scene):
    via_grpc = apis.submit_rpc(usd_scene["usdz"].read_bytes(), "still-life.usdz", SETTINGS, "g")
    assert not isinstance(via_grpc, Error), via_grpc
    via_client = apis.client.submit(str(usd_scene["usdz"]), settings=SETTINGS, name="c")
    # The same package converts to the same GLB: one stored scene.
    assert via_client["scene_sha256"] == via_grpc["scene_sha256"]
    _finished(apis, via_grpc)
    _finished(apis, via_client)


def _escaping(path: str) -> bytes:
    return ESCAPING_LAYER.replace("@PATH@", f"@{path}@").encode()


@pytest.mark.parametrize(
    ("path", "words"),
    [("/etc/hostname", "absolute"), ("../../etc/hostname", "'..'"), ("https://x.y/t.png", "URL")],
)
def test_an_asset_path_outside_the_upload_is_a_400_naming_prim_and_attribute(apis, path, words):
    before = len(apis.client.list()["jobs"])
    hostname = Path("/etc/hostname").read_text().strip() if Path("/etc/hostname").exists() else ""
    for answer in (
        apis.submit_rest(_escaping(path), "card.usda", SETTINGS, "bad"),
        apis.submit_rpc(_escaping(path), "card.usda", SETTINGS, "bad"),
    ):
        assert isinstance(answer, Error) and answer.kind == "invalid", answer
        assert answer.field == "scene:/World/Looks/M/Tex.inputs:file", answer
        assert words in answer.message, answer
        assert not hostname or hostname not in answer.message
    assert len(apis.client.list()["jobs"]) == before


def test_a_bundle_with_two_root_layers_is_refused_by_name(apis):
    archive = io.BytesIO()
    with zipfile.ZipFile(archive, "w") as z:
        z.writestr("a.usda", _escaping("t.png"))
        z.writestr("b.usda", _escaping("t.png"))
    answer = apis.submit_rest(archive.getvalue(), "two.zip", SETTINGS, "two")
    assert isinstance(answer, Error) and answer.kind == "invalid", answer
    assert "a.usda, b.usda" in answer.message


# ---------------------------------------------------------------- the worker, directly


def _worker_inspect(worker_binary: str, scene: Path) -> dict:
    run = subprocess.run([worker_binary, "inspect", "--json", str(scene)], capture_output=True,
                         text=True, timeout=120)  # fmt: skip
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout)


def _worker_render(worker_binary: str, scene: Path, out: Path, size: int, spp: int, *extra):
    args = [worker_binary, "render", str(scene), "-o", str(out), "--spp", str(spp), "--width",
            str(size), "--height", str(size), "--threads", "1", "--seed", "5", *extra]  # fmt: skip
    run = subprocess.run(args, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    ch = read_exr(str(out))
    return np.stack([ch["R"], ch["G"], ch["B"]], axis=-1)


def _floor_stage(folder: Path, half_width: float):
    """A stage (metres, Y up) with a 10 x 10 m Lambertian floor at y = 0 (diffuseColor 0.8,
    specular workflow with specularColor 0: glTF's specular factor 0) seen straight down by an
    orthographic camera 3 m above it whose square view is 2 half_width wide."""
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade

    stage = Usd.Stage.CreateNew(str(folder / "scene.usda"))
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    floor = UsdGeom.Mesh.Define(stage, "/Floor")
    floor.CreatePointsAttr([(-5, 0, 5), (5, 0, 5), (5, 0, -5), (-5, 0, -5)])
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
    camera.CreateProjectionAttr(UsdGeom.Tokens.orthographic)
    camera.CreateHorizontalApertureAttr(20.0 * half_width)  # tenths of a unit
    camera.CreateVerticalApertureAttr(20.0 * half_width)
    camera.CreateClippingRangeAttr(Gf.Vec2f(0.01, 100.0))
    camera.AddTranslateOp().Set(Gf.Vec3d(0, 3, 0))
    camera.AddRotateXOp().Set(-90.0)  # looking down
    return stage


def _pixel_radii(size: int, half_width: float, sub: int = 8) -> np.ndarray:
    """(size, size, sub * sub) distances from the view's centre of sub x sub points spread
    evenly over each pixel (the box filter's average is their mean)."""
    offsets = (np.arange(sub) + 0.5) / sub
    edges = np.arange(size)[:, None] + offsets[None, :]  # (size, sub)
    coord = (edges / size * 2.0 - 1.0) * half_width
    x = coord[None, :, None, :]
    z = coord[:, None, :, None]
    return np.sqrt(x * x + z * z).reshape(size, size, sub * sub)


def test_a_spot_light_is_accepted_and_lights_the_floor_by_gltfs_formula(worker_binary, tmp_path):
    """A treatAsPoint sphere light 2 m above the floor, shaped by a cone of 30 degrees with
    softness 0.5, converted and accepted by the workers' loader as a KHR_lights_punctual spot,
    renders the floor's radiance 0.8 E / pi, E the spot's irradiance by glTF's specification
    (intensity x ((cos a - cos outer) / (cos inner - cos outer))^2 clamped, x cos i / d^2);
    where UsdLux's cone is at full intensity that is UsdLux's own L pi r^2 cos i / d^2, and
    beyond the cone the floor is black."""
    from pxr import Gf, UsdLux

    half = 2.0
    stage = _floor_stage(tmp_path, half)
    light = UsdLux.SphereLight.Define(stage, "/Spot")
    light.CreateRadiusAttr(0.05)
    light.CreateTreatAsPointAttr(True)
    light.CreateIntensityAttr(1000.0)
    light.AddTranslateOp().Set(Gf.Vec3d(0, 2, 0))
    light.AddRotateXOp().Set(-90.0)
    shaping = UsdLux.ShapingAPI.Apply(light.GetPrim())
    shaping.CreateShapingConeAngleAttr(30.0)
    shaping.CreateShapingConeSoftnessAttr(0.5)
    stage.GetRootLayer().Save()
    conversion = convert_stage(tmp_path / "scene.usda", tmp_path, tmp_path)
    glb = tmp_path / "spot.glb"
    glb.write_bytes(conversion.glb)
    report = _worker_inspect(worker_binary, glb)
    assert report["ok"] and report["warnings"] == [], report
    assert "KHR_lights_punctual" in report["extensions_used"]
    json_len = int.from_bytes(conversion.glb[12:16], "little")
    doc = json.loads(conversion.glb[20 : 20 + json_len])
    (spot,) = doc["extensions"]["KHR_lights_punctual"]["lights"]
    assert spot["type"] == "spot"
    size = 64
    image = _worker_render(worker_binary, glb, tmp_path / "spot.exr", size, 64,
                           "--integrator", "direct")  # fmt: skip
    rho = _pixel_radii(size, half)
    d2 = 4.0 + rho**2
    cos_a = 2.0 / np.sqrt(d2)  # the angle off the spot's axis, and the floor's incidence
    cos_outer = math.cos(spot["spot"]["outerConeAngle"])
    cos_inner = math.cos(spot["spot"]["innerConeAngle"])
    ramp = np.clip((cos_a - cos_outer) / (cos_inner - cos_outer), 0.0, 1.0) ** 2
    irradiance = spot["intensity"] * ramp * cos_a / d2
    expected = (0.8 * irradiance / math.pi).mean(axis=2)
    full = (np.arccos(cos_a) <= math.radians(15.0)).all(axis=2)  # UsdLux's full intensity
    usd = (0.8 * 1000.0 * math.pi * 0.05**2 * cos_a / d2 / math.pi).mean(axis=2)
    dark = (np.arccos(cos_a) > math.radians(30.0)).all(axis=2)
    assert full.sum() > 100 and dark.sum() > 100
    for c in range(3):
        assert image[..., c][dark].max() < 1e-6 * expected.max()
        assert image[..., c][full] == pytest.approx(usd[full], rel=1e-3)
        assert np.abs(image[..., c] - expected).max() < 5e-3 * expected.max()
        assert image[..., c].sum() == pytest.approx(expected.sum(), rel=1e-3)


def test_a_mesh_whose_topology_changes_renders_each_shape_at_its_frames(worker_binary, tmp_path):
    """A triangle of area 1/2 at time code 1 and a square of area 1.44 from time code 10 (24
    per second), an emitter of radiance 1 on black seen straight down by an orthographic
    camera: rendered as farm frames 1 and 10 render them (`--time` = frame / fps, with fps =
    timeCodesPerSecond: docs/scenes.md), each image's ink, its pixel sum times a pixel's area
    (the box filter averages coverage), is that frame's shape's area."""
    from pxr import Gf, Sdf, UsdGeom, UsdShade

    half = 1.5
    stage = _floor_stage(tmp_path, half)
    stage.RemovePrim("/Floor")
    stage.SetStartTimeCode(1)
    stage.SetEndTimeCode(10)
    stage.SetTimeCodesPerSecond(24)
    mesh = UsdGeom.Mesh.Define(stage, "/Shape")
    mesh.CreateSubdivisionSchemeAttr("none")
    mesh.CreateDoubleSidedAttr(True)
    shapes = {1.0: [(0, 0), (1, 0), (0, 1)], 10.0: [(-0.6, -0.6), (0.6, -0.6), (0.6, 0.6),
                                                    (-0.6, 0.6)]}  # fmt: skip
    for t, corners in shapes.items():
        mesh.GetPointsAttr().Set([(x, 0.0, z) for x, z in corners], t)
        mesh.GetFaceVertexCountsAttr().Set([len(corners)], t)
        mesh.GetFaceVertexIndicesAttr().Set(list(range(len(corners))), t)
    glow = UsdShade.Material.Define(stage, "/Looks/Glow")
    shader = UsdShade.Shader.Define(stage, "/Looks/Glow/Surface")
    shader.CreateIdAttr("UsdPreviewSurface")
    shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(0, 0, 0))
    shader.CreateInput("emissiveColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(1, 1, 1))
    glow.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(glow)
    stage.GetRootLayer().Save()
    conversion = convert_stage(tmp_path / "scene.usda", tmp_path, tmp_path)
    assert not [w for w in conversion.warnings if w.startswith("/Shape")], conversion.warnings
    glb = tmp_path / "shape.glb"
    glb.write_bytes(conversion.glb)
    report = _worker_inspect(worker_binary, glb)
    assert report["ok"] and report["warnings"] == [], report
    size = 96
    pixel_area = (2.0 * half / size) ** 2
    for frame, area in ((1, 0.5), (5, 0.5), (10, 1.44)):
        image = _worker_render(worker_binary, glb, tmp_path / f"f{frame}.exr", size, 64,
                               "--time", repr(frame / 24.0))  # fmt: skip
        assert image.max() == pytest.approx(1.0, rel=1e-4)  # the emitter, where fully covered
        for c in range(3):
            assert image[..., c].sum() * pixel_area == pytest.approx(area, rel=1e-3)


TAKE = """#usda 1.0
(
    doc = "TAKE"
    upAxis = "Y"
)

def Mesh "Card"
{
    int[] faceVertexCounts = [4]
    int[] faceVertexIndices = [0, 1, 2, 3]
    point3f[] points = [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)]
    uniform token subdivisionScheme = "none"
}
"""


def test_two_uploads_converting_to_one_scene_each_name_their_own_source(apis, tmp_path):
    """Two .usda files that differ only in their documentation string convert to one GLB (one
    stored scene); each job's EXR names the upload it was submitted with, not the first."""
    takes = [TAKE.replace("TAKE", t).encode() for t in ("take one", "take two")]
    names = ["take-1.usda", "take-2.usda"]
    jobs = [apis.submit_rest(d, n, SETTINGS, "") for d, n in zip(takes, names, strict=True)]
    assert not any(isinstance(j, Error) for j in jobs), jobs
    assert jobs[0]["scene_sha256"] == jobs[1]["scene_sha256"]  # one scene, two sources
    for job, data, name in zip(jobs, takes, names, strict=True):
        _finished(apis, job)
        exr = tmp_path / f"{job['id']}.exr"
        exr.write_bytes(apis.client.image(job["id"], "exr"))
        spec = oiio.ImageInput.open(str(exr)).spec()
        assert (
            spec.getattribute("renderfarm:scene_source_sha256") == hashlib.sha256(data).hexdigest()
        )
        assert spec.getattribute("renderfarm:scene_source_filename") == name
