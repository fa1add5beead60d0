"""Scene bundles (.zip, .tar, .tar.gz) are read in memory, refused when unsafe, and packed into
the same .glb the client would have packed from the directory."""

from __future__ import annotations

import io
import tarfile
import zipfile
from pathlib import Path

import pytest

from renderfarm.domain.scenes.bundles import MAX_ENTRIES, bundle_to_glb, is_bundle, scene_upload
from renderfarm.domain.scenes.pack import pack_gltf
from renderfarm.errors import SceneError, TooLarge

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
GLTF = (EXAMPLES / "cornell-box.gltf").read_bytes()
BIN = (EXAMPLES / "cornell-box.bin").read_bytes()
LIMIT = 64 << 20


def _zip(entries: dict[str, bytes], symlinks: dict[str, str] | None = None) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for name, data in entries.items():
            z.writestr(name, data)
        for name, target in (symlinks or {}).items():
            info = zipfile.ZipInfo(name)
            info.external_attr = 0o120777 << 16
            z.writestr(info, target)
    return buf.getvalue()


def _tar(entries: dict[str, bytes], gz: bool = False, links: dict | None = None) -> bytes:
    links = links or {}
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz" if gz else "w") as t:
        for name, data in entries.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            t.addfile(info, io.BytesIO(data))
        for name, (target, kind) in links.items():
            info = tarfile.TarInfo(name)
            info.type = kind
            info.linkname = target
            t.addfile(info)
    return buf.getvalue()


CORNELL = {"scene/cornell-box.gltf": GLTF, "scene/cornell-box.bin": BIN}


@pytest.mark.parametrize("make", [_zip, _tar, lambda e: _tar(e, gz=True)],
                         ids=["zip", "tar", "tar.gz"])  # fmt: skip
def test_a_bundle_packs_to_the_same_glb_as_the_directory(make):
    data = make(CORNELL)
    assert is_bundle(data)
    glb, name = bundle_to_glb(data, "cornell.bundle", LIMIT)
    assert glb == pack_gltf(EXAMPLES / "cornell-box.gltf")
    assert name == "cornell-box.glb"


def test_non_bundles_pass_through_unchanged():
    glb = pack_gltf(EXAMPLES / "cornell-box.gltf")
    assert scene_upload(glb, "x.glb", LIMIT) == (glb, "x.glb")
    assert scene_upload(GLTF, "x.gltf", LIMIT) == (GLTF, "x.gltf")


@pytest.mark.parametrize(
    "entries, words",
    [
        ({**CORNELL, "../evil.txt": b"x"}, "climbs out of the bundle"),
        ({**CORNELL, "scene/../../evil.txt": b"x"}, "climbs out of the bundle"),
        ({**CORNELL, "/etc/evil": b"x"}, "absolute path"),
        ({**CORNELL, "C:/evil": b"x"}, "absolute path"),
        ({"scene/cornell-box.gltf": GLTF}, "not in the bundle"),
        ({"a.gltf": GLTF, "b.gltf": GLTF, "cornell-box.bin": BIN}, "exactly one .gltf"),
        ({"readme.txt": b"hello"}, "exactly one .gltf"),
        ({"scene.gltf": b"\x89PNG\r\n\x1a\n" + bytes(40)}, "not a glTF 2.0 file"),
    ],
    ids=["dotdot", "nested-dotdot", "absolute", "drive", "missing-file", "two-gltf",
         "no-gltf", "not-gltf"],
)  # fmt: skip
def test_unsafe_or_broken_zips_are_refused(entries, words):
    with pytest.raises(SceneError) as refused:
        bundle_to_glb(_zip(entries), "b.zip", LIMIT)
    assert words in refused.value.message


def test_a_gltf_uri_may_not_leave_the_bundle_but_may_climb_within_it():
    inside = GLTF.replace(b'"cornell-box.bin"', b'"../cornell-box.bin"')
    glb, _ = bundle_to_glb(_zip({"s/c.gltf": inside, "cornell-box.bin": BIN}), "b.zip", LIMIT)
    assert glb[:4] == b"glTF"
    gltf = GLTF.replace(b'"cornell-box.bin"', b'"../cornell-box.bin"')
    with pytest.raises(SceneError) as refused:
        bundle_to_glb(_zip({"c.gltf": gltf, "cornell-box.bin": BIN}), "b.zip", LIMIT)
    assert "outside the bundle" in refused.value.message
    assert refused.value.field == "scene.buffers[0].uri"


def test_symlinks_and_hard_links_are_refused():
    with pytest.raises(SceneError, match="symlink"):
        bundle_to_glb(_zip(CORNELL, symlinks={"scene/link": "/etc/passwd"}), "b.zip", LIMIT)
    with pytest.raises(SceneError, match="symlink"):
        bundle_to_glb(_tar(CORNELL, links={"l": ("/etc/passwd", tarfile.SYMTYPE)}), "b.tar",
                      LIMIT)  # fmt: skip
    with pytest.raises(SceneError, match="hard link"):
        bundle_to_glb(_tar(CORNELL, links={"l": ("scene/cornell-box.bin", tarfile.LNKTYPE)}),
                      "b.tar", LIMIT)  # fmt: skip


def test_size_and_count_limits():
    with pytest.raises(TooLarge):
        bundle_to_glb(_zip(CORNELL), "b.zip", len(BIN) // 2)
    # Compressed small, uncompressed over the limit: refused on the declared sizes.
    bomb = _tar({"scene.gltf": GLTF, "zeros.bin": bytes(8 << 20)}, gz=True)
    assert len(bomb) < 1 << 20
    with pytest.raises(TooLarge):
        bundle_to_glb(bomb, "bomb.tar.gz", 4 << 20)
    many = {f"f{i}.txt": b"" for i in range(MAX_ENTRIES + 1)}
    with pytest.raises(SceneError, match="entries"):
        bundle_to_glb(_zip(many), "many.zip", LIMIT)


def test_garbage_that_looks_like_an_archive_is_a_scene_error():
    with pytest.raises(SceneError):
        bundle_to_glb(b"PK\x03\x04" + bytes(100), "broken.zip", LIMIT)
    with pytest.raises(SceneError):
        bundle_to_glb(b"\x1f\x8b" + bytes(100), "broken.tar.gz", LIMIT)
