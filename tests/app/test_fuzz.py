"""Property-based fuzzing of the API from its own OpenAPI document (schemathesis): whatever the
input, the gateway answers without a server error."""

from __future__ import annotations

import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from schemathesis.checks import not_a_server_error

from tests.app.conftest import Service

EXAMPLES_PER_OPERATION = 40


def _operations(service: Service) -> list[schemathesis.APIOperation]:
    schema = schemathesis.openapi.from_asgi("/openapi.json", service.client.app)
    return [result.ok() for result in schema.get_all_operations()]  # type: ignore[union-attr]


def test_schema_covers_the_api(service: Service) -> None:
    names = {f"{op.method.upper()} {op.path}" for op in _operations(service)}
    assert {"POST /api/v1/captures", "POST /api/v1/jobs", "GET /api/v1/jobs/{job_id}",
            "DELETE /api/v1/jobs/{job_id}", "GET /api/v1/assets/{asset_id}/{name}"} <= names


@pytest.mark.slow
def test_no_server_errors(service: Service) -> None:
    for operation in _operations(service):
        @given(case=operation.as_strategy())
        @settings(max_examples=EXAMPLES_PER_OPERATION, deadline=None, database=None,
                  suppress_health_check=list(HealthCheck))
        def fuzz(case: schemathesis.Case) -> None:
            for headers in (service.auth, {}):
                response = case.call(headers=headers)
                case.validate_response(response, checks=[not_a_server_error])

        fuzz()
