"""The OpenAPI document the gateway serves declares its errors: every 4xx and 5xx of every
operation as application/problem+json with the problem schema, and the statuses any route can
answer (a bad parameter, the job store down, a key missing where one is needed)."""

from __future__ import annotations

from typing import Any

import pytest

from app.core.problems import PROBLEM_MEDIA_TYPE
from tests.app.conftest import Service

# The readiness probe's 503 is its report (status and checks), not a problem: probes read it.
NOT_PROBLEMS = {("GET", "/readyz", "503")}


@pytest.fixture(scope="module")
def operations(service: Service) -> dict[tuple[str, str], dict[str, Any]]:
    document = service.client.get("/openapi.json").json()
    return {(method.upper(), path): operation for path, item in document["paths"].items()
            for method, operation in item.items()}


def test_every_error_is_declared_as_problem_json(
        operations: dict[tuple[str, str], dict[str, Any]]) -> None:
    checked = 0
    for (method, path), operation in operations.items():
        for status, response in operation["responses"].items():
            if status[0] not in "45" or (method, path, status) in NOT_PROBLEMS:
                continue
            where = f"{method} {path} {status}"
            assert list(response.get("content", {})) == [PROBLEM_MEDIA_TYPE], where
            schema = response["content"][PROBLEM_MEDIA_TYPE]["schema"]
            assert {"type", "title", "status", "detail"} <= set(schema["required"]), where
            assert response["description"] not in ("", "Additional Response"), where
            checked += 1
    assert checked > 60  # about six per operation


def test_each_route_declares_the_statuses_it_can_answer(
        operations: dict[tuple[str, str], dict[str, Any]]) -> None:
    for (method, path), operation in operations.items():
        declared = set(operation["responses"])
        assert "500" in declared, f"{method} {path}"
        if not path.startswith("/api/v1/"):
            continue
        # Every API route reads the job store, takes a parameter or body, and may need a key.
        assert {"401", "422", "503"} <= declared, f"{method} {path}"
        if method == "POST":
            assert {"400", "408", "413"} <= declared, f"{method} {path}"
        if "{" in path:
            assert "404" in declared, f"{method} {path}"
        assert "WWW-Authenticate" in operation["responses"]["401"]["headers"]
        assert "Retry-After" in operation["responses"]["503"]["headers"]
    assert {"409", "415"} <= set(operations["POST", "/api/v1/captures"]["responses"])
    assert "416" in operations["GET", "/api/v1/assets/{asset_id}/{name}"]["responses"]


def test_every_api_route_needs_a_key_and_asset_reads_take_a_share_token(
        operations: dict[tuple[str, str], dict[str, Any]]) -> None:
    shareable = {("GET", "/api/v1/assets/{asset_id}"), ("GET", "/api/v1/assets/{asset_id}/{name}")}
    for (method, path), operation in operations.items():
        if not path.startswith("/api/v1/"):
            continue
        security = operation["security"]
        assert {"HTTPBearer": []} in security, f"{method} {path}"
        assert ({} in security) == ((method, path) in shareable), f"{method} {path}"
        if (method, path) in shareable:
            assert "share" in {p["name"] for p in operation["parameters"]}
    assert operations["GET", "/metrics"]["security"] == [{"HTTPBearer": []}]


def test_the_event_stream_declares_its_events(
        operations: dict[tuple[str, str], dict[str, Any]]) -> None:
    content = operations["GET", "/api/v1/jobs/{job_id}/events"]["responses"]["200"]["content"]
    assert list(content) == ["text/event-stream"]
    event = content["text/event-stream"]["schema"]
    assert event["properties"]["event"] == {"const": "job"}
    data = event["properties"]["data"]
    assert data["contentMediaType"] == "application/json"
    assert data["contentSchema"] == {"$ref": "#/components/schemas/JobPublic"}


def test_a_real_error_matches_its_declaration(service: Service) -> None:
    response = service.client.get("/api/v1/jobs/" + "0" * 32)
    assert response.status_code == 404
    assert response.headers["content-type"] == PROBLEM_MEDIA_TYPE
    assert set(response.json()) >= {"type", "title", "status", "detail"}
    unreadable = service.client.post("/api/v1/jobs", content=b"\xff\xfe{", headers={
        **service.auth, "Content-Type": "application/json"})
    assert unreadable.status_code == 400
    assert unreadable.json()["type"].endswith("/malformed-body")
    assert "UTF-8 JSON" in unreadable.json()["detail"]


def test_what_makes_a_resource_declares_its_location(
        operations: dict[tuple[str, str], dict[str, Any]]) -> None:
    for path, status in (("/api/v1/captures", "201"), ("/api/v1/jobs", "202"),
                         ("/api/v1/rigs", "201"), ("/api/v1/streams", "201")):
        success = operations["POST", path]["responses"][status]
        assert success["headers"]["Location"]["required"], path
        assert "application/json" in success["content"], path
