"""The README documents every job setting, server setting and CLI command."""

from pathlib import Path

from renderfarm.cli.parser import build_parser
from renderfarm.domain.jobspec import SETTINGS
from renderfarm.infra.config import Settings

README = (Path(__file__).resolve().parents[2] / "README.md").read_text()


def test_every_job_setting_is_documented_with_its_default():
    for s in SETTINGS:
        row = next((line for line in README.splitlines() if line.startswith(f"| `{s.name}` |")), "")
        assert row, f"job setting {s.name} missing from the README"
        default = "0" if s.default == 0.0 and s.kind is float else str(s.default)
        default = '""' if s.default == "" else default
        default = str(s.default).lower() if s.kind is bool else default
        assert f"`{default}`" in row, f"README default of {s.name} is not {default}"


def test_every_server_setting_is_documented():
    for name in Settings.model_fields:
        assert f"`RENDERFARM_{name.upper()}`" in README, name
        assert f"`--{name.replace('_', '-')}`" in README, name


def test_every_cli_command_is_documented():
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    for command in sub.choices:
        assert f"renderfarm {command}" in README, command


def test_every_rest_endpoint_is_documented():
    """Generated check: each path of the OpenAPI document has a row in the README's table."""
    from unittest.mock import MagicMock

    from renderfarm.api.rest import create_app

    farm = MagicMock()
    farm.settings.http_host = farm.settings.grpc_host = "127.0.0.1"
    app = create_app(farm, MagicMock())
    for path, methods in app.openapi()["paths"].items():
        for method in methods:
            shown = path.split("?")[0]
            assert f"`{method.upper()} {shown}" in README, f"{method.upper()} {path} undocumented"


def test_every_grpc_method_is_documented():
    from renderfarm.v1 import jobs_pb2

    for method in jobs_pb2.DESCRIPTOR.services_by_name["JobService"].methods:
        assert f"`{method.name}`" in README, method.name


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
        assert f"`{name}" in README, name
