"""bench/cycles_parity.py's Lambert copy (--lambert-dielectrics): only opaque dielectrics lose
their specular layer, and the copy is a valid GLB with the same binary chunk."""

from __future__ import annotations

import importlib
from pathlib import Path

from renderfarm.domain.scenes.glb import build_glb, parse_json, split_glb

BENCH = Path(__file__).resolve().parents[1] / "bench"


def harness(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCH))
    return importlib.import_module("cycles_parity")


def test_only_opaque_dielectrics_get_specular_factor_zero(monkeypatch, tmp_path):
    parity = harness(monkeypatch)
    blob = bytes(range(16))
    document = {
        "asset": {"version": "2.0"},
        "materials": [
            {"name": "Plastic", "pbrMetallicRoughness": {"metallicFactor": 0.0}},
            {"name": "DefaultIsMetal", "pbrMetallicRoughness": {}},
            {"name": "NoPbrIsMetal"},
            {"name": "HalfMetal", "pbrMetallicRoughness": {"metallicFactor": 0.5}},
            {
                "name": "Glass",
                "pbrMetallicRoughness": {"metallicFactor": 0.0},
                "extensions": {"KHR_materials_transmission": {"transmissionFactor": 1.0}},
            },
            {
                "name": "Tinted",
                "pbrMetallicRoughness": {"metallicFactor": 0.0},
                "extensions": {
                    "KHR_materials_specular": {
                        "specularFactor": 0.7,
                        "specularTexture": {"index": 0},
                    },
                    "KHR_materials_clearcoat": {"clearcoatFactor": 1.0},
                },
            },
        ],
    }
    scene = tmp_path / "scene.glb"
    scene.write_bytes(build_glb(document, blob))
    copy, changed = parity.without_dielectric_specular(scene, tmp_path / "out")
    assert changed == ["Plastic", "Tinted"]
    json_chunk, copy_blob = split_glb(copy.read_bytes(), copy.name)
    result = parse_json(json_chunk, copy.name)
    materials = {m["name"]: m for m in result["materials"]}
    assert materials["Plastic"]["extensions"]["KHR_materials_specular"] == {"specularFactor": 0.0}
    # The texture goes with the factor; the coat stays.
    assert materials["Tinted"]["extensions"] == {
        "KHR_materials_specular": {"specularFactor": 0.0},
        "KHR_materials_clearcoat": {"clearcoatFactor": 1.0},
    }
    before = {m["name"]: m for m in document["materials"]}
    for name in ("DefaultIsMetal", "NoPbrIsMetal", "HalfMetal", "Glass"):
        assert materials[name] == before[name], name
    assert result["extensionsUsed"] == ["KHR_materials_specular"]
    assert copy_blob[: len(blob)] == blob
    # The original is untouched.
    original = parse_json(split_glb(scene.read_bytes(), scene.name)[0], scene.name)
    assert original == document
