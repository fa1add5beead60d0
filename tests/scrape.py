"""A farm's Prometheus metric as the tests read it from its /metrics exposition."""

from __future__ import annotations

import re

import httpx


def metric(url: str, name: str) -> float:
    """The value of metric `name` at the server `url`, summed over its label sets;
    AssertionError when the exposition has no sample of it."""
    text = httpx.get(f"{url}/metrics", timeout=10).text
    pattern = re.compile(rf"{re.escape(name)}(\{{[^}}]*\}})? (\S+)$")
    values = [float(m.group(2)) for m in map(pattern.match, text.splitlines()) if m]
    assert values, f"{name} missing from /metrics"
    return sum(values)
