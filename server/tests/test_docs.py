"""The README documents every job setting, server setting and CLI command."""

from pathlib import Path

from renderfarm.cli import build_parser
from renderfarm.config import Settings
from renderfarm.jobspec import SETTINGS

README = (Path(__file__).resolve().parents[2] / "README.md").read_text()


def test_every_job_setting_is_documented_with_its_default():
    for s in SETTINGS:
        row = next((line for line in README.splitlines() if line.startswith(f"| `{s.name}` |")), "")
        assert row, f"job setting {s.name} missing from the README"
        default = "0" if s.default == 0.0 and s.kind is float else str(s.default)
        default = '""' if s.default == "" else default
        assert f"`{default}`" in row, f"README default of {s.name} is not {default}"


def test_every_server_setting_is_documented():
    for name in Settings.model_fields:
        assert f"`RENDERFARM_{name.upper()}`" in README, name
        assert f"`--{name.replace('_', '-')}`" in README, name


def test_every_cli_command_is_documented():
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    for command in sub.choices:
        assert f"renderfarm {command}" in README, command
