"""The job settings are declared once (jobspec.SETTINGS): the proto, the worker's reading of it,
the REST document and docs/settings.md are held to that table here."""

from __future__ import annotations

import re
from dataclasses import fields
from pathlib import Path

import pytest
from google.protobuf.descriptor import FieldDescriptor

from renderfarm.domain import jobspec
from renderfarm.domain.jobspec import SETTINGS, JobSettings, Sampler
from renderfarm.v1 import jobs_pb2

ROOT = Path(__file__).resolve().parents[2]
MESSAGE = jobs_pb2.RenderSettings.DESCRIPTOR
GENERATED = re.compile(
    r"<!-- settings table: generated.*?-->\n(.*?)<!-- end of settings table -->", re.S
)

# The proto type each kind of setting may take, by the range the table gives it.
INTEGER_TYPES = {
    FieldDescriptor.TYPE_UINT32: (0, 2**32 - 1),
    FieldDescriptor.TYPE_UINT64: (0, 2**64 - 1),
    FieldDescriptor.TYPE_INT32: (-(2**31), 2**31 - 1),
    FieldDescriptor.TYPE_INT64: (-(2**63), 2**63 - 1),
}


def test_every_setting_is_a_field_of_render_settings_and_nothing_else_is():
    assert sorted(f.name for f in MESSAGE.fields) == sorted(s.field for s in SETTINGS)
    for s in SETTINGS:
        f = MESSAGE.fields_by_name[s.field]
        assert f.number == s.proto, s.name
        assert f.has_presence, f"{s.field} must be `optional` (unset = the default)"


@pytest.mark.parametrize("setting", SETTINGS, ids=lambda s: s.name)
def test_the_field_type_holds_the_settings_range(setting):
    f = MESSAGE.fields_by_name[setting.field]
    if setting.choices:
        assert f.type == FieldDescriptor.TYPE_ENUM
        assert f.enum_type.name == setting.kind.__name__
        prefix = setting.name.upper() + "_"
        assert [v.name for v in f.enum_type.values] == [prefix + "UNSPECIFIED"] + [
            prefix + c.upper() for c in setting.choices
        ]
        assert f.enum_type.values[0].number == 0
    elif setting.kind is int:
        assert f.type in INTEGER_TYPES, f.type
        lo, hi = INTEGER_TYPES[f.type]
        bound = jobspec.SETTING_BY_NAME[setting.bounded_by] if setting.bounded_by else setting
        top = getattr(jobspec.Limits(), bound.limit) if bound.limit else bound.maximum
        assert setting.minimum is not None and lo <= setting.minimum
        if bound.limit in jobspec.CONFIGURABLE_LIMITS:
            top = 2**31  # an operator may raise a limit: the field must still hold it
        assert top is not None and top <= hi
    else:
        expected = {
            float: FieldDescriptor.TYPE_DOUBLE,
            bool: FieldDescriptor.TYPE_BOOL,
            str: FieldDescriptor.TYPE_STRING,
        }[setting.kind]
        assert f.type == expected


def test_job_settings_dataclass_is_the_table():
    assert [(f.name, f.default) for f in fields(JobSettings)] == [
        (s.name, s.default) for s in SETTINGS
    ]
    assert JobSettings().sampler == Sampler.SOBOL == "sobol"
    for s in SETTINGS:
        if s.choices:
            assert s.default in s.choices, s.name
        elif s.minimum is not None and not isinstance(s.default, bool):
            top = getattr(jobspec.Limits(), s.limit) if s.limit else s.maximum
            assert s.minimum <= s.default and (top is None or s.default <= top), s.name


def _worker_reader() -> str:
    """The worker's source that maps RenderSettings (wherever the layout puts it)."""
    for path in sorted((ROOT / "worker" / "src").rglob("*.cpp")):
        if "_test" in path.name:
            continue
        text = path.read_text()
        if "bool settings_from_proto(" in text:
            return text
    raise AssertionError("no worker source defines settings_from_proto")


def test_the_worker_reads_exactly_the_settings_marked_for_it():
    source = _worker_reader()
    for s in SETTINGS:
        read = re.search(rf"\.{s.field}\(\)", source) is not None
        assert read == s.worker, (
            f"settings.{s.name}: the table says worker={s.worker}, the worker "
            f"{'reads' if read else 'does not read'} {s.field}()"
        )


def test_every_enum_value_maps_to_a_worker_type():
    source = _worker_reader()
    for s in SETTINGS:
        if not s.worker:  # the server's own (adaptive)
            continue
        prefix = s.name.upper() + "_"
        for choice in s.choices:
            assert f"case pb::{prefix}{choice.upper()}:" in source, (s.name, choice)


def test_settings_doc_is_the_generated_table():
    """docs/settings.md holds the table `python -m renderfarm settings --markdown` prints;
    regenerate it with `make settings-doc` after changing jobspec.SETTINGS."""
    text = (ROOT / "docs" / "settings.md").read_text()
    found = GENERATED.search(text)
    assert found, "docs/settings.md has no generated settings table"
    assert found.group(1) == jobspec.settings_markdown(), "stale: run `make settings-doc`"
