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


def test_coverage_copy_makes_every_material_a_flat_emitter_and_drops_the_lights(
    monkeypatch, tmp_path
):
    parity = harness(monkeypatch)
    blob = bytes(range(16))
    document = {
        "asset": {"version": "2.0"},
        "extensionsUsed": ["KHR_lights_punctual", "KHR_materials_emissive_strength"],
        "extensions": {"KHR_lights_punctual": {"lights": [{"type": "point"}]}},
        "nodes": [{"name": "Lamp", "extensions": {"KHR_lights_punctual": {"light": 0}}}],
        "materials": [
            {"name": "Floor", "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}},
            {
                "name": "Glow",
                "emissiveFactor": [1.0, 1.0, 1.0],
                "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": 6.0}},
            },
        ],
    }
    scene = tmp_path / "scene.glb"
    scene.write_bytes(build_glb(document, blob))
    copy = parity.coverage_copy(scene, tmp_path / "out")
    json_chunk, copy_blob = split_glb(copy.read_bytes(), copy.name)
    result = parse_json(json_chunk, copy.name)
    for i, material in enumerate(result["materials"]):
        assert material["emissiveFactor"] == list(parity.COVERAGE_COLOURS[i])
        assert material["pbrMetallicRoughness"]["baseColorFactor"] == [0.0, 0.0, 0.0, 1.0]
        assert material["extensions"] == {"KHR_materials_specular": {"specularFactor": 0.0}}
    assert "extensions" not in result or "KHR_lights_punctual" not in result["extensions"]
    assert result["nodes"] == [{"name": "Lamp", "extensions": {}}]
    assert result["extensionsUsed"] == [
        "KHR_materials_emissive_strength",
        "KHR_materials_specular",
    ]
    assert copy_blob[: len(blob)] == blob


def test_frames_of_an_animated_scene_are_at_the_farms_frame_times(monkeypatch):
    parity = harness(monkeypatch)

    class Args:
        frame = [[1, 24], [48]]
        fps = None

    assert parity.frames_of("animated_shot", Args, parity=True) == [
        {"frame": f, "fps": 24.0, "time": f / 24.0} for f in (1, 24, 48)
    ]
    # A still parity scene in the suite ignores --frame; a file takes it at --fps or 24.
    assert parity.frames_of("glass", Args, parity=True) == [None]
    Args.fps = 30.0
    assert parity.frames_of("shot", Args, parity=False)[2] == {
        "frame": 48,
        "fps": 30.0,
        "time": 1.6,
    }
    Args.frame = []
    assert parity.frames_of("shot", Args, parity=False) == [None]
    assert [f["frame"] for f in parity.frames_of("animated_shot", Args, parity=True)] == [
        1,
        24,
        48,
    ]


def test_edge_mask_marks_both_sides_of_a_step_and_nothing_flat(monkeypatch):
    parity = harness(monkeypatch)
    import numpy as np

    image = np.full((8, 8, 3), 0.2)
    image[:, 4:] = 1.0
    mask = parity.edge_mask(image)
    assert mask[:, 3:5].all()
    assert not mask[:, :3].any() and not mask[:, 5:].any()
