"""docs/ documents every job setting, server setting, CLI command, REST endpoint, gRPC method
and metric (docs/settings.md, docs/usage.md, docs/api.md)."""

from pathlib import Path

from renderfarm.cli.parser import build_parser
from renderfarm.infra.config import Settings

DOCS = Path(__file__).resolve().parents[2] / "docs"
SETTINGS_MD = (DOCS / "settings.md").read_text()
USAGE_MD = (DOCS / "usage.md").read_text()
API_MD = (DOCS / "api.md").read_text()


# The job settings table is generated: test_settings_schema.py holds it to jobspec.SETTINGS.


def test_every_server_setting_is_documented():
    for name in Settings.model_fields:
        assert f"`RENDERFARM_{name.upper()}`" in SETTINGS_MD, name
        assert f"`--{name.replace('_', '-')}`" in SETTINGS_MD, name


def test_every_cli_command_is_documented():
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    for command in sub.choices:
        assert f"renderfarm {command}" in USAGE_MD, command


def test_every_rest_endpoint_is_documented():
    """Generated check: each path of the OpenAPI document has a row in docs/api.md's table."""
    from unittest.mock import MagicMock

    from renderfarm.api.rest import create_app

    farm = MagicMock()
    farm.settings.http_host = farm.settings.grpc_host = "127.0.0.1"
    app = create_app(farm, MagicMock())
    for path, methods in app.openapi()["paths"].items():
        for method in methods:
            shown = path.split("?")[0]
            assert f"`{method.upper()} {shown}" in API_MD, f"{method.upper()} {path} undocumented"


def test_every_grpc_method_is_documented():
    from renderfarm.v1 import jobs_pb2

    for method in jobs_pb2.DESCRIPTOR.services_by_name["JobService"].methods:
        assert f"`{method.name}`" in API_MD, method.name


def test_every_metric_is_documented():
    from unittest.mock import MagicMock

    from renderfarm.api.metrics import Metrics

    farm = MagicMock()
    farm.scheduler.jobs = {}
    farm.scheduler.leases = {}
    farm.sessions = {}
    farm.store.errors = 0
    for family in Metrics(farm).registry.collect():
        name = family.name + ("_total" if family.type == "counter" else "")
        assert f"`{name}" in API_MD, name
