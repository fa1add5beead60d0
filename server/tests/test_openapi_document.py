"""web/openapi.json, from which the dashboard's TypeScript types are generated, is the document
the server serves: regenerate it with `make openapi` after changing a REST model."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _generator():
    spec = importlib.util.spec_from_file_location(
        "openapi_json", ROOT / "scripts" / "openapi_json.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_committed_document_is_the_servers():
    committed = (ROOT / "web" / "openapi.json").read_text()
    assert committed == _generator().document(), "web/openapi.json is stale: run `make openapi`"


def test_enumerated_settings_are_enums_in_the_document():
    schema = json.loads((ROOT / "web" / "openapi.json").read_text())["components"]["schemas"]
    props = schema["JobSettings"]["properties"]
    assert props["sampler"]["enum"] == ["sobol", "halton", "stratified", "independent"]
    assert props["integrator"]["enum"] == ["path", "direct", "ao"]
    assert props["tile_size"]["minimum"] == 8 and props["tile_size"]["maximum"] == 512
    assert props["environment_intensity"]["exclusiveMinimum"] == 0
