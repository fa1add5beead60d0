"""Scene validation (inspect_scene) and packing of .gltf + files into one .glb (pack_gltf)."""

import base64
import copy
import hashlib
import json
import os
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from renderfarm.domain.scenes.pack import pack_gltf
from renderfarm.domain.scenes.validate import (
    SceneInfo,
    inspect_scene,
    job_variants,
    resolve_variant,
)
from renderfarm.errors import SceneError, SettingsError

REPO = Path(__file__).resolve().parents[2]
EXAMPLES = REPO / "examples"
CORNELL_GLTF = EXAMPLES / "cornell-box.gltf"
CORNELL_BIN = EXAMPLES / "cornell-box.bin"

PNG_BYTES = b"\x89PNG\r\n\x1a\n" + b"\x00\x00\x00\rIHDR" + bytes(17)
TRIANGLE = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype="<f4").tobytes()  # 36 bytes


# --------------------------------------------------------------------------------------
# Helpers, written independently of renderfarm.domain.scenes.
# --------------------------------------------------------------------------------------


def data_uri(data: bytes, mime: str = "application/octet-stream") -> str:
    return f"data:{mime};base64," + base64.b64encode(data).decode()


def triangle_doc(uri: str | None = None, byte_length: int = len(TRIANGLE)) -> dict:
    """A minimal valid glTF document with one triangle; buffer 0 uses ``uri`` if given."""
    buffer = {"byteLength": byte_length}
    if uri is not None:
        buffer["uri"] = uri
    return {
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
        "accessors": [
            {
                "bufferView": 0,
                "componentType": 5126,
                "count": 3,
                "type": "VEC3",
                "min": [0, 0, 0],
                "max": [1, 1, 0],
            }
        ],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": len(TRIANGLE)}],
        "buffers": [buffer],
    }


def embedded_gltf(doc: dict | None = None) -> bytes:
    return json.dumps(doc or triangle_doc(data_uri(TRIANGLE))).encode()


def glb_chunks(*chunks: tuple[int, bytes], version: int = 2, length: int | None = None) -> bytes:
    body = b"".join(struct.pack("<II", len(data), kind) + data for kind, data in chunks)
    total = 12 + len(body) if length is None else length
    return struct.pack("<4sII", b"glTF", version, total) + body


def padded_json(doc: dict) -> bytes:
    raw = json.dumps(doc).encode()
    return raw + b" " * (-len(raw) % 4)


JSON, BIN = 0x4E4F534A, 0x004E4942


def make_glb(doc: dict, blob: bytes | None) -> bytes:
    chunks = [(JSON, padded_json(doc))]
    if blob is not None:
        chunks.append((BIN, blob + b"\0" * (-len(blob) % 4)))
    return glb_chunks(*chunks)


def read_glb(data: bytes) -> tuple[dict, bytes]:
    magic, version, length = struct.unpack_from("<4sII", data)
    assert (magic, version, length) == (b"glTF", 2, len(data))
    json_len, json_type = struct.unpack_from("<II", data, 12)
    assert json_type == JSON
    doc = json.loads(data[20 : 20 + json_len])
    offset = 20 + json_len
    bin_len, bin_type = struct.unpack_from("<II", data, offset)
    assert bin_type == BIN
    assert offset + 8 + bin_len == len(data)
    return doc, data[offset + 8 : offset + 8 + bin_len]


def accessor_array(doc: dict, blob: bytes, index: int) -> np.ndarray:
    accessor = doc["accessors"][index]
    view = doc["bufferViews"][accessor["bufferView"]]
    dtype = {5126: "<f4", 5123: "<u2", 5125: "<u4"}[accessor["componentType"]]
    width = {"SCALAR": 1, "VEC3": 3}[accessor["type"]]
    assert view.get("byteStride", np.dtype(dtype).itemsize * width) == (
        np.dtype(dtype).itemsize * width
    )
    start = view.get("byteOffset", 0) + accessor.get("byteOffset", 0)
    array = np.frombuffer(blob, dtype=dtype, count=accessor["count"] * width, offset=start)
    return array.reshape(accessor["count"], width)


def refused(data: bytes, *fragments: str, field: str | None = None, **kwargs) -> SceneError:
    with pytest.raises(SceneError) as info:
        inspect_scene(data, **kwargs)
    message = str(info.value)
    for fragment in fragments:
        assert fragment in message, f"{fragment!r} not in {message!r}"
    if field is not None:
        assert info.value.field == field
    return info.value


# --------------------------------------------------------------------------------------
# The Cornell box example
# --------------------------------------------------------------------------------------


def test_example_files_pass_their_own_check():
    script = EXAMPLES / "make_cornell_box.py"
    result = subprocess.run(
        [sys.executable, str(script), "--check"], capture_output=True, text=True, check=False
    )
    assert result.returncode == 0, result.stderr


def test_packing_the_cornell_box_keeps_the_vertex_data():
    packed = pack_gltf(CORNELL_GLTF)
    info = inspect_scene(packed, "cornell-box.glb")
    assert info == SceneInfo(
        sha256=hashlib.sha256(packed).hexdigest(),
        format="glb",
        size_bytes=len(packed),
        meshes=4,
        nodes=5,
        extensions_required=(),
        # The emissive quad is node 3, "light": a light group, and the environment another.
        light_groups={"light": [3], "environment": []},
    )

    original = json.loads(CORNELL_GLTF.read_text())
    original_bin = CORNELL_BIN.read_bytes()
    doc, blob = read_glb(packed)
    assert doc["buffers"] == [{"byteLength": len(blob)}]
    assert all(view["buffer"] == 0 for view in doc["bufferViews"])

    total_vertices = 0
    for mesh_before, mesh_after in zip(original["meshes"], doc["meshes"], strict=True):
        for prim_before, prim_after in zip(
            mesh_before["primitives"], mesh_after["primitives"], strict=True
        ):
            for semantic in ("POSITION", "NORMAL"):
                before = accessor_array(original, original_bin, prim_before["attributes"][semantic])
                after = accessor_array(doc, blob, prim_after["attributes"][semantic])
                np.testing.assert_array_equal(before, after)
            before = accessor_array(original, original_bin, prim_before["indices"])
            after = accessor_array(doc, blob, prim_after["indices"])
            np.testing.assert_array_equal(before, after)
            total_vertices += len(after)
    assert total_vertices == 16 * 6  # 16 quads, 32 triangles

    # The light quad sits 0.5 mm below the ceiling, in metres.
    light = accessor_array(doc, blob, doc["meshes"][3]["primitives"][0]["attributes"]["POSITION"])
    np.testing.assert_array_equal(light[:, 1], np.float32(0.5483))


def test_packing_is_deterministic_and_a_glb_passes_through_unchanged(tmp_path):
    packed = pack_gltf(CORNELL_GLTF)
    assert pack_gltf(str(CORNELL_GLTF)) == packed
    glb = tmp_path / "box.glb"
    glb.write_bytes(packed)
    assert pack_gltf(glb) == packed


def test_unpacked_cornell_gltf_is_refused_naming_the_external_file():
    error = refused(
        CORNELL_GLTF.read_bytes(), "cornell-box.bin", ".glb", ".glb", filename="cornell-box.gltf"
    )
    assert error.field == "scene.buffers[0].uri"


# --------------------------------------------------------------------------------------
# Accepted scenes
# --------------------------------------------------------------------------------------


def test_self_contained_gltf_is_accepted():
    data = embedded_gltf()
    info = inspect_scene(data, "tri.gltf")
    assert info.format == "gltf"
    assert (info.meshes, info.nodes, info.size_bytes) == (1, 1, len(data))
    assert info.sha256 == hashlib.sha256(data).hexdigest()


def test_glb_is_accepted_and_reports_required_extensions():
    doc = triangle_doc()
    doc["extensionsUsed"] = doc["extensionsRequired"] = ["KHR_materials_emissive_strength"]
    info = inspect_scene(make_glb(doc, TRIANGLE))
    assert info.format == "glb"
    assert info.extensions_required == ("KHR_materials_emissive_strength",)


def test_glb_with_unknown_trailing_chunk_is_accepted():
    data = glb_chunks((JSON, padded_json(triangle_doc())), (BIN, TRIANGLE), (0x12345678, b"xxxx"))
    assert inspect_scene(data).format == "glb"


# --------------------------------------------------------------------------------------
# Refusals
# --------------------------------------------------------------------------------------


def test_empty_input_is_refused():
    refused(b"", "empty", filename="a.glb", field="scene")


def test_input_over_the_size_limit_is_refused():
    data = embedded_gltf()
    refused(data, "limit", str(len(data) - 1), max_bytes=len(data) - 1)
    assert inspect_scene(data, max_bytes=len(data)).size_bytes == len(data)


def test_png_is_refused_as_not_gltf():
    refused(PNG_BYTES, "scene.gltf is not a glTF 2.0 file", "image", filename="scene.gltf")


def test_text_file_is_refused_as_not_gltf():
    refused(
        b"hello, this is a README\n",
        "notes.txt is not a glTF 2.0 file",
        "text",
        filename="notes.txt",
    )


def test_random_binary_is_refused_as_not_gltf():
    refused(bytes(range(256)), "is not a glTF 2.0 file", "glTF")


@pytest.mark.parametrize(
    "data, fragment",
    [
        (b"glTF\x02\x00\x00", "truncated"),
        (glb_chunks((JSON, padded_json(triangle_doc())), (BIN, TRIANGLE), version=1), "version 1"),
        (glb_chunks((JSON, padded_json(triangle_doc())), (BIN, TRIANGLE), length=9999), "9999"),
        (glb_chunks((BIN, TRIANGLE), (JSON, padded_json(triangle_doc()))), "first chunk"),
        (glb_chunks((JSON, padded_json(triangle_doc()) + b"x")), "multiple of 4"),
        (glb_chunks((JSON, b"{}  "), (JSON, b"{}  ")), "more than one JSON"),
        (
            glb_chunks((JSON, padded_json(triangle_doc())), (BIN, TRIANGLE), (BIN, TRIANGLE)),
            "BIN chunk",
        ),
        (
            glb_chunks((JSON, padded_json(triangle_doc())), (0x1, b"abcd"), (BIN, TRIANGLE)),
            "BIN chunk must directly follow",
        ),
        (glb_chunks((JSON, b"")), "JSON chunk is empty"),
        (glb_chunks(), "no JSON chunk"),
    ],
    ids=lambda value: value if isinstance(value, str) else "",
)
def test_broken_glb_container_is_refused(data, fragment):
    refused(data, "damaged GLB" if fragment != "version 1" else "GLB", fragment, field="scene")


def test_glb_chunk_running_past_the_end_is_refused():
    good = make_glb(triangle_doc(), TRIANGLE)
    # Claim a longer BIN chunk than present, keeping the header length consistent.
    json_len = struct.unpack_from("<I", good, 12)[0]
    bin_header = 20 + json_len
    bad = bytearray(good)
    struct.pack_into("<I", bad, bin_header, len(TRIANGLE) + 8)
    refused(bytes(bad), "runs past the end")


def test_glb_buffer_without_uri_needs_a_bin_chunk():
    refused(make_glb(triangle_doc(), None), "no BIN chunk", field="scene.buffers[0].uri")


def test_glb_buffer_larger_than_bin_chunk_is_refused():
    refused(make_glb(triangle_doc(byte_length=40), TRIANGLE), "larger than its data", "40")


@pytest.mark.parametrize(
    "text, fragment",
    [
        (b"{ not json", "not valid glTF JSON"),
        (b'{"asset": {"version": "2.0"}, "meshes": [NaN]}', "not valid glTF JSON"),
        (b"{\xff\xfe}", "UTF-8"),
    ],
)
def test_invalid_json_is_refused(text, fragment):
    refused(text, fragment, field="scene")


def test_json_top_level_must_be_an_object():
    # Starts with "{" is required to be treated as glTF at all; a list is "not glTF".
    refused(b"[1, 2, 3]", "not a glTF 2.0 file")


def mutated(change) -> bytes:
    doc = triangle_doc(data_uri(TRIANGLE))
    change(doc)
    return embedded_gltf(doc)


@pytest.mark.parametrize(
    "change, fragments, field",
    [
        (lambda d: d.pop("asset"), ("asset",), "scene.asset"),
        (lambda d: d["asset"].pop("version"), ("asset.version is missing",), "scene.asset.version"),
        (lambda d: d["asset"].update(version="1.0"), ("'1.0'", "2.0"), "scene.asset.version"),
        (lambda d: d["asset"].update(version=2), ("asset.version",), "scene.asset.version"),
        (lambda d: d["asset"].update(minVersion="2.1"), ("minVersion",), "scene.asset.minVersion"),
        (lambda d: d.pop("meshes"), ("no meshes",), "scene.meshes"),
        (lambda d: d.update(meshes=[]), ("no meshes",), "scene.meshes"),
        (
            lambda d: d["buffers"][0].update(uri="triangle.bin"),
            ("'triangle.bin'", "self-contained", ".glb", ".glb"),
            "scene.buffers[0].uri",
        ),
        (
            lambda d: d["buffers"][0].update(uri="https://example.com/t.bin"),
            ("'https://example.com/t.bin'", ".glb"),
            "scene.buffers[0].uri",
        ),
        (
            lambda d: d.update(images=[{"uri": "textures/wood.png"}]),
            ("image 0", "'textures/wood.png'", ".glb"),
            "scene.images[0].uri",
        ),
        (
            lambda d: d["buffers"][0].pop("uri"),
            ("buffer 0 has no uri",),
            "scene.buffers[0].uri",
        ),
        (
            lambda d: d["buffers"][0].update(byteLength=100),
            ("byteLength is 100", "larger than its data", "36 bytes"),
            "scene.buffers[0].byteLength",
        ),
        (
            lambda d: d["buffers"][0].update(uri="data:application/octet-stream;base64,@@@@"),
            ("invalid base64",),
            "scene.buffers[0].uri",
        ),
        (
            lambda d: d["bufferViews"][0].update(byteOffset=4),
            ("bufferView 0", "past the end of buffer 0"),
            "scene.bufferViews[0]",
        ),
        (
            lambda d: d["bufferViews"][0].update(buffer=3),
            ("buffer 3",),
            "scene.bufferViews[0].buffer",
        ),
    ],
)
def test_invalid_gltf_content_is_refused(change, fragments, field):
    refused(mutated(change), *fragments, field=field)


def test_embedded_image_data_uri_is_accepted():
    data = mutated(lambda d: d.update(images=[{"uri": data_uri(PNG_BYTES, "image/png")}]))
    assert inspect_scene(data).format == "gltf"


# --------------------------------------------------------------------------------------
# Packing
# --------------------------------------------------------------------------------------


def write_gltf(directory: Path, doc: dict, name: str = "scene.gltf") -> Path:
    path = directory / name
    path.write_text(json.dumps(doc))
    return path


def test_pack_merges_buffers_and_images(tmp_path):
    (tmp_path / "tex").mkdir()
    (tmp_path / "my data.bin").write_bytes(TRIANGLE[:30])  # 30 bytes: forces padding
    (tmp_path / "tex" / "wood.PNG").write_bytes(PNG_BYTES)
    (tmp_path / "tex" / "bark.jpeg").write_bytes(b"\xff\xd8\xff\xe0" + bytes(20))
    second = TRIANGLE + TRIANGLE
    doc = triangle_doc("my%20data.bin", byte_length=30)
    doc["bufferViews"] = [
        {"buffer": 0, "byteOffset": 0, "byteLength": 24},
        {"buffer": 1, "byteOffset": 36, "byteLength": 36},
    ]
    doc["accessors"] = [
        {"bufferView": 1, "componentType": 5126, "count": 3, "type": "VEC3"},
        {"bufferView": 0, "componentType": 5126, "count": 2, "type": "VEC3"},
    ]
    doc["buffers"].append({"uri": data_uri(second), "byteLength": len(second)})
    doc["images"] = [
        {"uri": "tex/wood.PNG"},
        {"uri": "./tex/bark.jpeg"},
        {"uri": data_uri(b"RIFF\0\0\0\0WEBPVP8 ", "image/webp")},
    ]
    packed = pack_gltf(write_gltf(tmp_path, doc))
    assert inspect_scene(packed).format == "glb"

    out, blob = read_glb(packed)
    assert out["buffers"] == [{"byteLength": len(blob)}]
    assert len(blob) % 4 == 0
    views = out["bufferViews"]
    assert all(v["buffer"] == 0 and v["byteOffset"] % 4 == 0 for v in views)
    assert views[1]["byteOffset"] == 32 + 36  # buffer 1 starts at the aligned offset 32
    np.testing.assert_array_equal(
        accessor_array(out, blob, 0), np.frombuffer(TRIANGLE, "<f4").reshape(3, 3)
    )
    assert [img["mimeType"] for img in out["images"]] == ["image/png", "image/jpeg", "image/webp"]
    jpeg = b"\xff\xd8\xff\xe0" + bytes(20)
    for image, expected in zip(out["images"][:2], [PNG_BYTES, jpeg], strict=True):
        assert "uri" not in image
        view = views[image["bufferView"]]
        assert blob[view["byteOffset"] : view["byteOffset"] + view["byteLength"]] == expected


def test_pack_refuses_a_path_escaping_the_directory(tmp_path):
    (tmp_path / "secret.bin").write_bytes(TRIANGLE)  # exists, so only the escape is wrong
    scene_dir = tmp_path / "scene"
    scene_dir.mkdir()
    path = write_gltf(scene_dir, triangle_doc("../secret.bin"))
    with pytest.raises(SceneError, match="outside the .gltf's directory") as info:
        pack_gltf(path)
    assert "../secret.bin" in str(info.value)
    assert info.value.field == "scene.buffers[0].uri"


def test_pack_refuses_percent_encoded_escape(tmp_path):
    (tmp_path / "secret.bin").write_bytes(TRIANGLE)
    scene_dir = tmp_path / "scene"
    scene_dir.mkdir()
    with pytest.raises(SceneError, match="outside"):
        pack_gltf(write_gltf(scene_dir, triangle_doc("%2E%2E/secret.bin")))


@pytest.mark.parametrize("uri", ["/etc/passwd", "file:///etc/passwd", "%2Fetc%2Fpasswd"])
def test_pack_refuses_absolute_paths(tmp_path, uri):
    with pytest.raises(SceneError, match="absolute|not a relative path") as info:
        pack_gltf(write_gltf(tmp_path, triangle_doc(uri)))
    assert info.value.field == "scene.buffers[0].uri"


def test_pack_refuses_remote_urls(tmp_path):
    with pytest.raises(SceneError, match="not a relative path"):
        pack_gltf(write_gltf(tmp_path, triangle_doc("https://example.com/t.bin")))


@pytest.mark.skipif(not hasattr(os, "symlink"), reason="needs symlinks")
def test_pack_refuses_a_symlink_escaping_the_directory(tmp_path):
    (tmp_path / "secret.bin").write_bytes(TRIANGLE)
    scene_dir = tmp_path / "scene"
    scene_dir.mkdir()
    (scene_dir / "data.bin").symlink_to(tmp_path / "secret.bin")
    with pytest.raises(SceneError, match="outside the .gltf's directory"):
        pack_gltf(write_gltf(scene_dir, triangle_doc("data.bin")))


def test_pack_follows_a_symlink_inside_the_directory(tmp_path):
    (tmp_path / "real.bin").write_bytes(TRIANGLE)
    (tmp_path / "link.bin").symlink_to(tmp_path / "real.bin")
    packed = pack_gltf(write_gltf(tmp_path, triangle_doc("link.bin")))
    assert read_glb(packed)[1] == TRIANGLE


def test_pack_refuses_missing_files(tmp_path):
    with pytest.raises(SceneError, match="does not exist") as info:
        pack_gltf(write_gltf(tmp_path, triangle_doc("missing.bin")))
    assert "missing.bin" in str(info.value)
    with pytest.raises(SceneError, match="does not exist"):
        pack_gltf(tmp_path / "nothing.gltf")


def test_pack_refuses_a_buffer_file_shorter_than_byte_length(tmp_path):
    (tmp_path / "short.bin").write_bytes(TRIANGLE[:20])
    with pytest.raises(SceneError, match="larger than its data"):
        pack_gltf(write_gltf(tmp_path, triangle_doc("short.bin")))


def test_pack_names_avif_images_by_their_extension_or_their_ftyp_box(tmp_path):
    """EXT_texture_avif's images: image/avif from the file name, or from the ISO-BMFF box
    'ftyp' with brand avif (or avis, a sequence) when the name says nothing."""
    (tmp_path / "t.bin").write_bytes(TRIANGLE)
    avif = bytes([0, 0, 0, 0x1C]) + b"ftypavif" + bytes(16)
    avis = bytes([0, 0, 0, 0x1C]) + b"ftypavis" + bytes(16)
    (tmp_path / "leaf.AVIF").write_bytes(avif)
    (tmp_path / "bark.img").write_bytes(avif)
    (tmp_path / "moss.img").write_bytes(avis)
    doc = triangle_doc("t.bin")
    doc["images"] = [{"uri": "leaf.AVIF"}, {"uri": "bark.img"}, {"uri": "moss.img"}]
    out, _blob = read_glb(pack_gltf(write_gltf(tmp_path, doc)))
    assert [img["mimeType"] for img in out["images"]] == ["image/avif"] * 3


def test_pack_refuses_image_of_unknown_type(tmp_path):
    (tmp_path / "t.bin").write_bytes(TRIANGLE)
    (tmp_path / "picture.xyz").write_bytes(b"not an image")
    doc = triangle_doc("t.bin")
    doc["images"] = [{"uri": "picture.xyz"}]
    with pytest.raises(SceneError, match="unknown type") as info:
        pack_gltf(write_gltf(tmp_path, doc))
    assert info.value.field == "scene.images[0].uri"


def test_pack_refuses_non_gltf_files(tmp_path):
    png = tmp_path / "picture.png"
    png.write_bytes(PNG_BYTES)
    with pytest.raises(SceneError, match="not a glTF 2.0 file"):
        pack_gltf(png)
    text = tmp_path / "notes.txt"
    text.write_text("just some notes\n")
    with pytest.raises(SceneError, match="not a glTF 2.0 file"):
        pack_gltf(text)


def test_pack_result_is_validated(tmp_path):
    """The packed container is checked like an upload (accessors are the server's loader's)."""
    doc = triangle_doc(data_uri(TRIANGLE))
    doc["bufferViews"][0]["byteOffset"] = 4
    with pytest.raises(SceneError, match="past the end of buffer 0"):
        pack_gltf(write_gltf(tmp_path, doc))


def test_pack_does_not_modify_the_source(tmp_path):
    (tmp_path / "t.bin").write_bytes(TRIANGLE)
    doc = triangle_doc("t.bin")
    path = write_gltf(tmp_path, copy.deepcopy(doc))
    pack_gltf(path)
    assert json.loads(path.read_text()) == doc


def _variants_doc(names):
    doc = triangle_doc(data_uri(TRIANGLE))
    doc["extensionsUsed"] = ["KHR_materials_variants"]
    doc["extensions"] = {"KHR_materials_variants": {"variants": [{"name": n} for n in names]}}
    return doc


def test_a_scenes_variants_are_read_and_a_job_names_one_by_name_or_index():
    data = json.dumps(_variants_doc(["Red", "Blue", "7"])).encode()
    info = inspect_scene(data, "shoe.gltf")
    assert info.variants == ("Red", "Blue", "7")
    assert resolve_variant("", info.variants) == -1  # the default materials
    assert resolve_variant("Blue", info.variants) == 1
    assert resolve_variant("0", info.variants) == 0  # an index first
    assert resolve_variant("7", info.variants) == 2  # not an index here: the name
    for bad in ("blue", "3x", "Purple"):
        with pytest.raises(SettingsError) as e:
            resolve_variant(bad, info.variants)
        assert e.value.field == "settings.variant"
        assert "0 'Red', 1 'Blue', 2 '7'" in str(e.value)
    with pytest.raises(SettingsError, match="it has none"):
        resolve_variant(
            "Red", inspect_scene(json.dumps(triangle_doc(data_uri(TRIANGLE))).encode()).variants
        )


def test_variant_all_names_every_variant_and_wins_over_a_variant_named_all():
    names = ("Red", "all", "Blue")
    assert job_variants("all", names) == names  # every variant, in order
    assert job_variants("1", names) == () and job_variants("", names) == ()  # one, or none
    with pytest.raises(SettingsError) as e:
        job_variants("Purple", names)
    assert e.value.field == "settings.variant"
    with pytest.raises(SettingsError) as e:
        job_variants("all", ())
    assert e.value.field == "settings.variant" and "has none" in str(e.value)
