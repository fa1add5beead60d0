"""The USD conversion's child process (infra/usd_import.py): what leaves it is a GLB or a
refusal the API can report, whatever happens inside.

A child that dies of its limits is a SceneError saying which limits (never a 500 or a hang); a
stage that names a layer through the server's USD search path is refused before the resolver
could look there; a refusal inside the child keeps its prim and attribute as the field.
"""

from __future__ import annotations

import asyncio
import io
import json
import subprocess
import sys
import zipfile

import pytest

pytest.importorskip("pxr")
from pxr import Sdf  # noqa: E402

from renderfarm.errors import SceneError  # noqa: E402
from renderfarm.infra import landlock, usd_import  # noqa: E402
from renderfarm.infra.usd_import import UsdImporter  # noqa: E402

CARD = """#usda 1.0
(
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


def test_a_card_converts_to_a_glb_named_after_the_upload(tmp_path):
    result = asyncio.run(UsdImporter(tmp_path).convert(CARD.encode(), "card.usda"))
    assert result.glb[:4] == b"glTF" and result.filename == "card.glb"
    assert result.warnings == [] and result.environment_data is None
    assert not any(tmp_path.iterdir())  # its working directory is gone


def test_a_child_that_runs_out_of_memory_is_refused_naming_the_limits(tmp_path, monkeypatch):
    # Far less address space than Python with usd-core needs to start (about 1.2 GB).
    monkeypatch.setattr(usd_import, "BASE_ADDRESS_SPACE", 300 * 2**20)
    importer = UsdImporter(tmp_path, memory_mb=1, cpu_seconds=20)
    with pytest.raises(SceneError) as refused:
        asyncio.run(importer.convert(CARD.encode(), "card.usda"))
    assert "cannot be converted within the server's limits" in refused.value.message
    assert "1 MB of memory" in refused.value.message and refused.value.field == "scene"


def test_the_servers_usd_search_path_is_not_searched(tmp_path, monkeypatch):
    """A bare name (a search path for USD's default resolver) must name a file of the upload:
    the server's PXR_AR_DEFAULT_SEARCH_PATH is neither passed on nor consulted."""
    outside = tmp_path / "library"
    outside.mkdir()
    (outside / "prop.usda").write_text(CARD)
    monkeypatch.setenv("PXR_AR_DEFAULT_SEARCH_PATH", str(outside))
    layer = CARD + '\ndef "Prop" (\n    references = @prop.usda@</Card>\n)\n{\n}\n'
    archive = io.BytesIO()
    with zipfile.ZipFile(archive, "w") as z:
        z.writestr("shot.usda", layer)
    with pytest.raises(SceneError) as refused:
        asyncio.run(UsdImporter(tmp_path / "work").convert(archive.getvalue(), "shot.zip"))
    assert refused.value.field == "scene:/Prop.references"
    assert "names no file of the upload" in refused.value.message


_CLIPPED = """#usda 1.0
(
    startTimeCode = 1
    endTimeCode = 1
)
def Mesh "Thing" (
    clips = {
        dictionary default = {
            string templateAssetPath = "../../../outside/clip.#.usda"
            double templateStartTime = 1
            double templateEndTime = 1
            double templateStride = 1
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

_TRIANGLE = """#usda 1.0
def Mesh "Tri"
{
    uniform token subdivisionScheme = "none"
    int[] faceVertexCounts = [3]
    int[] faceVertexIndices = [0, 1, 2]
    point3f[] points = [(0, 0, 0), (9, 0, 0), (0, 9, 0)]
}
"""


def _zip(files: dict[str, bytes | str]) -> bytes:
    archive = io.BytesIO()
    with zipfile.ZipFile(archive, "w") as z:
        for name, content in files.items():
            z.writestr(name, content)
    return archive.getvalue()


def test_a_value_clip_template_climbing_out_of_the_upload_is_refused(tmp_path):
    """The child lays the upload out in WORK/usd-*/upload: ../../../outside is tmp_path/outside,
    where a clip layer waits with a triangle that USD would compose into the mesh."""
    (tmp_path / "outside").mkdir()
    clip = '#usda 1.0\ndef Mesh "Geo"\n{\n    point3f[] points.timeSamples = {\n'
    clip += "        1: [(0, 0, 0), (7, 0, 0), (0, 7, 0)],\n    }\n}\n"
    (tmp_path / "outside" / "clip.1.usda").write_text(clip)
    with pytest.raises(SceneError) as refused:
        asyncio.run(
            UsdImporter(tmp_path / "work").convert(_zip({"shot.usda": _CLIPPED}), "shot.zip")
        )
    assert refused.value.field == "scene:/Thing.clips[default].templateAssetPath"
    assert "'..'" in refused.value.message


def _package(tmp_path, sub: str) -> bytes:
    """A .usdz (usd-core's writer): root.usda referencing sub.usda inside the package."""
    src = tmp_path / "src"
    src.mkdir(exist_ok=True)
    root = '#usda 1.0\n(\n    defaultPrim = "Asset"\n)\n'
    root += 'def "Asset" (\n    references = @./sub.usda@</Part>\n)\n{\n}\n'
    (src / "root.usda").write_text(root)
    (src / "sub.usda").write_text(sub)
    writer = Sdf.ZipFileWriter.CreateNew(str(tmp_path / "inner.usdz"))
    writer.AddFile(str(src / "root.usda"), "root.usda")
    writer.AddFile(str(src / "sub.usda"), "sub.usda")
    writer.Save()
    return (tmp_path / "inner.usdz").read_bytes()


_SHOT = '#usda 1.0\ndef "Prop" (\n    references = @./inner.usdz@\n)\n{\n}\n'


def test_an_absolute_path_inside_a_nested_package_is_refused(tmp_path):
    """inner.usdz[sub.usda] references an absolute path outside the upload (a same-named
    sub.usda beside the package as a decoy): refused, naming the packaged layer."""
    (tmp_path / "outside.usda").write_text(_TRIANGLE)
    sub = f'#usda 1.0\ndef "Part" (\n    references = @{tmp_path / "outside.usda"}@</Tri>\n)\n'
    sub += "{\n}\n"
    decoy = '#usda 1.0\ndef "Part"\n{\n}\n'
    shot = _SHOT.replace("./inner.usdz", "./assets/inner.usdz")
    package = _package(tmp_path, sub)
    bundle = _zip({"shot.usda": shot, "assets/inner.usdz": package, "assets/sub.usda": decoy})
    with pytest.raises(SceneError) as refused:
        asyncio.run(UsdImporter(tmp_path / "work").convert(bundle, "shot.zip"))
    assert refused.value.field == "scene:/Part.references"
    assert "assets/inner.usdz[sub.usda]" in refused.value.message
    assert "absolute" in refused.value.message


def test_a_multi_layer_nested_package_converts(tmp_path):
    """The same package whose sub.usda holds the triangle itself, with nothing beside it, at
    the bundle's top beside the shot's layer (which is the root layer)."""
    sub = _TRIANGLE.replace('def Mesh "Tri"', 'def Mesh "Part"')
    bundle = _zip({"shot.usda": _SHOT, "inner.usdz": _package(tmp_path, sub)})
    result = asyncio.run(UsdImporter(tmp_path / "work").convert(bundle, "shot.zip"))
    json_len = int.from_bytes(result.glb[12:16], "little")
    doc = json.loads(result.glb[20 : 20 + json_len])
    (position,) = [a for a in doc["accessors"] if a["type"] == "VEC3"]
    assert position["max"] == pytest.approx([0.09, 0.09, 0.0])  # 9 cm, USD's default unit


def test_a_child_that_spins_past_its_cpu_time_is_refused_naming_the_limits(tmp_path):
    """The importer's limits applied to a child that only burns CPU (given as the importer's
    Python): prlimit's CPU-time limit of 1 s ends it (SIGXCPU), and the upload is refused
    naming the limits, not a server error."""
    spin = tmp_path / "spin.py"
    spin.write_text(f"#!{sys.executable}\nwhile True:\n    pass\n")
    spin.chmod(0o755)
    importer = UsdImporter(tmp_path / "work", cpu_seconds=1, python=str(spin))
    with pytest.raises(SceneError) as refused:
        asyncio.run(importer.convert(CARD.encode(), "card.usda"))
    assert "cannot be converted within the server's limits" in refused.value.message
    assert "1 s of CPU time" in refused.value.message and refused.value.field == "scene"


_TEXTURED = """#usda 1.0
def Mesh "Card" (
    prepend apiSchemas = ["MaterialBindingAPI"]
)
{
    int[] faceVertexCounts = [4]
    int[] faceVertexIndices = [0, 1, 2, 3]
    point3f[] points = [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)]
    rel material:binding = </Card/M>
    def Material "M"
    {
        token outputs:surface.connect = </Card/M/Surface.outputs:surface>
        def Shader "Surface"
        {
            uniform token info:id = "UsdPreviewSurface"
            color3f inputs:diffuseColor.connect = </Card/M/Tex.outputs:rgb>
            token outputs:surface
        }
        def Shader "Tex"
        {
            uniform token info:id = "UsdUVTexture"
            asset inputs:file = @textures/wood.png@
            float3 outputs:rgb
        }
    }
}
"""


def test_a_layer_uploaded_without_its_textures_is_told_to_come_as_a_bundle(tmp_path):
    """A .usda naming textures/wood.png uploaded alone: the 400 names the texture's prim and
    attribute and says to upload a .zip bundle; the same layer in a bundle with other files but
    not that one is refused without the advice."""
    importer = UsdImporter(tmp_path / "work")
    with pytest.raises(SceneError) as alone:
        asyncio.run(importer.convert(_TEXTURED.encode(), "card.usda"))
    assert alone.value.field == "scene:/Card/M/Tex.inputs:file"
    assert "names no file of the upload" in alone.value.message
    assert ".zip bundle" in alone.value.message
    bundle = _zip({"card.usda": _TEXTURED, "textures/other.png": b"\x89PNG\r\n\x1a\n"})
    with pytest.raises(SceneError) as bundled:
        asyncio.run(importer.convert(bundle, "card.zip"))
    assert bundled.value.field == "scene:/Card/M/Tex.inputs:file"
    assert "names no file of the upload" in bundled.value.message
    assert ".zip" not in bundled.value.message


def test_the_child_confines_itself_where_the_kernel_can(tmp_path):
    result = asyncio.run(UsdImporter(tmp_path / "work").convert(CARD.encode(), "card.usda"))
    if landlock.abi_version() > 0:
        assert result.confinement.startswith("enforced (Landlock ABI"), result.confinement
    else:
        assert result.confinement.startswith("unavailable:"), result.confinement


_CONFINED = """
import json, sys
from pathlib import Path
from renderfarm.infra.landlock import confine
from renderfarm.infra.usd_import import readable_paths
upload, out, secret = (Path(a) for a in sys.argv[1:4])
status = confine(readable_paths(upload), [out])
seen = {}
for name, path, mode in [("upload", upload / "card.usda", "r"), ("secret", secret, "r"),
                         ("write out", out / "scene.glb", "w"),
                         ("write upload", upload / "new.usda", "w")]:
    try:
        open(path, mode).close()
        seen[name] = "allowed"
    except PermissionError:
        seen[name] = "denied"
print(json.dumps({"status": status, "seen": seen}))
"""


def test_the_confined_child_reads_the_upload_and_nothing_else(tmp_path):
    """The child's own rule set (readable_paths) applied by a process that then tries what a
    stage might: the upload is readable, a file outside it is not (a file of the same user, in
    the same temporary folder), the output folder is writable and the upload is not."""
    if landlock.abi_version() == 0:
        pytest.skip("the kernel has no Landlock")
    upload, out = tmp_path / "upload", tmp_path / "out"
    upload.mkdir()
    out.mkdir()
    (upload / "card.usda").write_text(CARD)
    (tmp_path / "secret.txt").write_text("the server's")
    done = subprocess.run(
        [sys.executable, "-c", _CONFINED, str(upload), str(out), str(tmp_path / "secret.txt")],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    answer = json.loads(done.stdout.strip().splitlines()[-1])
    assert answer["status"].startswith("enforced"), answer
    assert answer["seen"] == {
        "upload": "allowed", "secret": "denied", "write out": "allowed", "write upload": "denied",
    }  # fmt: skip


def test_without_landlock_confine_changes_nothing_and_says_why(tmp_path, monkeypatch):
    monkeypatch.setattr(landlock, "abi_version", lambda: 0)
    (tmp_path / "anywhere.txt").write_text("x")
    status = landlock.confine([str(tmp_path / "nothing")], [])
    assert status.startswith("unavailable:") and "Landlock" in status
    assert (tmp_path / "anywhere.txt").read_text() == "x"  # still readable: nothing applied
