"""KHR_xmp_json_ld: the asset's metadata packet read from a stored scene's JSON (a GLB's JSON
chunk, or a .gltf's text) for the EXR header."""

from __future__ import annotations

import json

import pytest

from renderfarm.domain.scenes import metadata
from renderfarm.domain.scenes.glb import build_glb

PACKET = {
    "@context": {"dc": "http://purl.org/dc/elements/1.1/"},
    "dc:title": "Sneaker",
    "dc:creator": {"@list": ["A. Maker"]},
    "dc:rights": "CC-BY 4.0",
}


def document(packet_index=0, packets=None) -> dict:
    return {
        "asset": {"version": "2.0", "extensions": {"KHR_xmp_json_ld": {"packet": packet_index}}},
        "extensionsUsed": ["KHR_xmp_json_ld"],
        "extensions": {"KHR_xmp_json_ld": {"packets": [PACKET] if packets is None else packets}},
    }


def test_a_glbs_json_chunk_gives_the_assets_packet():
    glb = build_glb(document(), b"\0" * 16)
    head = glb[: metadata.JSON_CHUNK_OFFSET]
    length = metadata.json_chunk_length(head)
    assert length is not None
    raw = glb[metadata.JSON_CHUNK_OFFSET : metadata.JSON_CHUNK_OFFSET + length]
    text = metadata.xmp_attribute(raw)
    assert text is not None and json.loads(text) == PACKET
    # Keys sorted and compact: the header is a function of the scene, not of dict order.
    assert text == json.dumps(PACKET, sort_keys=True, separators=(",", ":"))


def test_a_gltf_is_json_throughout():
    raw = json.dumps(document()).encode()
    assert metadata.json_chunk_length(raw[: metadata.JSON_CHUNK_OFFSET]) is None
    assert json.loads(metadata.xmp_attribute(raw)) == PACKET


@pytest.mark.parametrize(
    "doc",
    [
        document(packet_index=1),  # no such packet
        document(packet_index=True),  # a boolean is no index
        document(packet_index="0"),
        document(packets=["not an object"]),
        {"asset": {"version": "2.0"}},  # no metadata at all
        {"asset": {"version": "2.0", "extensions": {"KHR_xmp_json_ld": {"packet": 0}}}},
    ],
)
def test_missing_or_malformed_metadata_gives_none(doc):
    assert metadata.xmp_attribute(json.dumps(doc).encode()) is None


def test_text_that_is_not_json_gives_none():
    assert metadata.xmp_attribute(b"\xff\xfe not json") is None
