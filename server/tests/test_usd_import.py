"""The USD conversion's child process (infra/usd_import.py): what leaves it is a GLB or a
refusal the API can report, whatever happens inside.

A child that dies of its limits is a SceneError saying which limits (never a 500 or a hang); a
stage that names a layer through the server's USD search path is refused before the resolver
could look there; a refusal inside the child keeps its prim and attribute as the field.
"""

from __future__ import annotations

import asyncio
import io
import zipfile

import pytest

pytest.importorskip("pxr")

from renderfarm.errors import SceneError  # noqa: E402
from renderfarm.infra import usd_import  # noqa: E402
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
