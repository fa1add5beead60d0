"""Light groups found in a glTF document (domain/light_groups.py): which nodes emit, how groups
are named and merged, the environment last, and the limit."""

from __future__ import annotations

import pytest

from renderfarm.domain import channels, light_groups
from renderfarm.domain.jobspec import parse_settings
from renderfarm.errors import SettingsError

LIGHT = {"KHR_lights_punctual": {"light": 0}}


def doc(nodes, meshes=None, materials=None, **more) -> dict:
    return {
        "scenes": [{"nodes": list(range(len(nodes)))}],
        "nodes": nodes,
        "meshes": meshes or [],
        "materials": materials or [],
        **more,
    }


def mesh(material=None, mode=4, mappings=()) -> dict:
    primitive = {"attributes": {"POSITION": 0}, "mode": mode}
    if material is not None:
        primitive["material"] = material
    if mappings:
        primitive["extensions"] = {"KHR_materials_variants": {"mappings": [
            {"material": m, "variants": [0]} for m in mappings]}}  # fmt: skip
    return {"primitives": [primitive]}


MATERIALS = [
    {"name": "plain"},
    {"name": "glow", "emissiveFactor": [0, 0.5, 0]},
    {"name": "flat", "extensions": {"KHR_materials_unlit": {}}},
    {"name": "dark", "emissiveFactor": [0, 0, 0], "emissiveTexture": {"index": 0}},
]


def test_lights_and_emissive_meshes_are_groups_by_name_and_the_environment_last():
    nodes = [
        {"name": "key", "extensions": LIGHT},
        {"name": "table", "mesh": 0},  # plain: lights nothing
        {"name": "panel", "mesh": 1},  # emissive
        {"mesh": 1},  # unnamed: nodes[3]
        {"name": "sign", "mesh": 2},  # unlit shows its colour
        {"name": "off", "mesh": 3},  # an emissive texture times a zero factor emits nothing
        {"name": "Rim Light.001", "extensions": LIGHT},  # made safe for layer names
    ]
    meshes = [mesh(0), mesh(1), mesh(2), mesh(3)]
    groups = light_groups.scene_groups(doc(nodes, meshes, MATERIALS))
    assert groups == {"key": [0], "panel": [2], "nodes_3_": [3], "sign": [4],
                      "Rim_Light_001": [6], "environment": []}  # fmt: skip
    assert channels.group_names(light_groups.encode(groups))[-1] == "environment"


def test_extras_light_group_names_a_group_nodes_share():
    nodes = [
        {"name": "lamp1", "extras": {"light_group": "lamps"}, "extensions": LIGHT},
        {"name": "bulb", "mesh": 0, "extras": {"light_group": "lamps"}},
        {"name": "lamp2", "extras": {"light_group": ""}, "extensions": LIGHT},  # empty: name
        {"name": "sky", "extras": {"light_group": "environment"}, "extensions": LIGHT},
    ]
    groups = light_groups.scene_groups(doc(nodes, [mesh(1)], MATERIALS))
    # A node in the group `environment` shares the environment's, which stays last.
    assert groups == {"lamps": [0, 1], "lamp2": [2], "environment": [3]}


def test_what_may_emit_counts_variants_animations_points_and_only_the_rendered_scene():
    nodes = [
        {"name": "variant", "mesh": 0},  # plain, glow in a variant
        {"name": "animated", "mesh": 1},  # plain material 4 whose emission an animation sets
        {"name": "dots", "mesh": 2},  # points: unlit without normals
        {"name": "elsewhere", "extensions": LIGHT},  # not in the rendered scene
        {"name": "child", "extensions": LIGHT},
    ]
    nodes[1]["children"] = [4]
    materials = [*MATERIALS, {"name": "dimmer"}]
    pointer = {"KHR_animation_pointer": {"pointer": "/materials/4/emissiveFactor"}}
    document = doc(nodes, [mesh(0, mappings=(1,)), mesh(4), mesh(0, mode=0)], materials,
                   animations=[{"channels": [{"sampler": 0, "target": {
                       "path": "pointer", "extensions": pointer}}]}])  # fmt: skip
    document["scenes"] = [{"nodes": [0, 1, 2]}]
    assert light_groups.scene_groups(document) == {
        "variant": [0], "animated": [1], "dots": [2], "child": [4], "environment": [],
    }  # fmt: skip


def test_too_many_groups_are_refused_naming_the_setting():
    nodes = [{"name": f"l{i}", "extensions": LIGHT} for i in range(light_groups.MAX_GROUPS)]
    groups = light_groups.scene_groups(doc(nodes))
    assert len(groups) == light_groups.MAX_GROUPS + 1  # and the environment
    with pytest.raises(SettingsError, match="has 33 light groups .* extras.light_group") as e:
        light_groups.check_count(groups)
    assert e.value.field == "settings.aovs"
    del groups["l0"]
    light_groups.check_count(groups)


def test_the_setting_keeps_its_names_and_belongs_to_jobs_that_ask_for_groups():
    value = {"Key": [0], "environment": []}
    s = parse_settings({"aovs": ["light_groups"], "light_groups": value})
    assert s.light_groups == '{"Key":[0],"environment":[]}'  # compact, case kept
    assert parse_settings({"light_groups": value}).light_groups == ""  # no light_groups asked
    for bad in ("[1]", {"a": [-1]}, {"a": "x"}, "{"):
        with pytest.raises(SettingsError) as e:
            parse_settings({"aovs": "light_groups", "light_groups": bad})
        assert e.value.field == "settings.light_groups"


def test_the_setting_is_the_servers_and_forms_leave_it_out():
    from renderfarm.domain.jobspec import setting_docs

    derived = [d["name"] for d in setting_docs() if d["derived"]]
    assert derived == ["light_groups"]
