"""Property-based fuzzing of the REST API from its own OpenAPI document (schemathesis).

Every operation of /openapi.json except the endless SSE stream (/watch) gets generated requests,
valid and invalid: the server must never answer 5xx, and every answer (status code, content
type, body) must match what the schema declares. Bounded: a few examples per operation; no
generated request can start a render (a scene is either random bytes or an unknown hash)."""

from __future__ import annotations

import schemathesis
from hypothesis import HealthCheck, given, settings
from schemathesis.checks import (
    content_type_conformance,
    not_a_server_error,
    response_schema_conformance,
    status_code_conformance,
)

CHECKS = [
    not_a_server_error,
    status_code_conformance,
    content_type_conformance,
    response_schema_conformance,
]


def test_no_server_errors_and_every_answer_matches_the_schema(farm):
    schema = schemathesis.openapi.from_url(f"{farm.url}/openapi.json")
    operations = [r.ok() for r in schema.exclude(path_regex=r"/watch$").get_all_operations()]
    assert len(operations) >= 10
    tested = []
    calls = []
    for operation in operations:

        @given(case=operation.as_strategy())
        @settings(
            max_examples=25,
            deadline=None,
            suppress_health_check=list(HealthCheck),
            derandomize=True,
            database=None,
        )
        def fuzz(case):
            calls.append(case.call_and_validate(checks=CHECKS).status_code)

        fuzz()
        tested.append(operation.label)
    assert any("POST /api/v1/jobs" == label for label in tested), tested
    assert len(calls) >= 5 * len(operations), f"only {len(calls)} requests were made"
    print(f"{len(calls)} requests over {len(operations)} operations; statuses {sorted(set(calls))}")
