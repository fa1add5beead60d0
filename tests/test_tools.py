"""tests/tools.py require_tool: a missing tool skips the test on a developer's machine and fails
it in CI (CI=true, as GitHub Actions and GitLab set it), where nothing may be skipped silently."""

from __future__ import annotations

import pytest

from .tools import require_tool


@pytest.mark.parametrize("ci", [None, "true", "false"])
def test_an_available_tool_is_neither_skipped_nor_failed(monkeypatch, ci):
    if ci is None:
        monkeypatch.delenv("CI", raising=False)
    else:
        monkeypatch.setenv("CI", ci)
    assert require_tool(True, "present") is None


@pytest.mark.parametrize("ci", [None, "", "false", "0"])
def test_a_missing_tool_skips_outside_ci(monkeypatch, ci):
    if ci is None:
        monkeypatch.delenv("CI", raising=False)
    else:
        monkeypatch.setenv("CI", ci)
    with pytest.raises(pytest.skip.Exception, match="^frobnicator: apt install frob$"):
        require_tool(False, "frobnicator: apt install frob")


@pytest.mark.parametrize("ci", ["true", "TRUE", "1", "yes"])
def test_a_missing_tool_fails_in_ci(monkeypatch, ci):
    monkeypatch.setenv("CI", ci)
    with pytest.raises(pytest.fail.Exception, match="^missing in CI: frobnicator$"):
        require_tool(False, "frobnicator")
