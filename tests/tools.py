"""Tests that need a tool from the machine: skipped where it is missing on a developer's
machine, failed in CI (CI=true), where scripts/install-deps.sh must have installed it."""

from __future__ import annotations

import os

import pytest


def require_tool(available: bool, what: str) -> None:
    """Skip (or, in CI, fail) the calling test unless `available`; `what` says what is missing
    and which install step provides it."""
    if available:
        return
    if os.environ.get("CI", "").lower() in ("true", "1", "yes"):
        pytest.fail(f"missing in CI: {what}", pytrace=False)
    pytest.skip(what)
