"""Property-based fuzzing of the API from its own OpenAPI document (schemathesis): the gateway
keeps the contract it publishes (status codes, media types, bodies and auth, by schemathesis's
default checks), and whatever the input, it answers without a server error."""

from __future__ import annotations

import hashlib
from collections.abc import Iterator
from typing import Any

import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from hypothesis.strategies import SearchStrategy
from schemathesis import GenerationMode
from schemathesis.checks import not_a_server_error, positive_data_acceptance
from schemathesis.config import SchemathesisConfig

from tests.app.conftest import Service
from workers.models import Asset

EXAMPLES_PER_OPERATION = 40
# Per operation and kind of input: keeps the contract run to about ten seconds.
CONTRACT_EXAMPLES = 12

# Checks an operation cannot pass, each for the reason given; every other default check runs.
# positive_data_acceptance wants every schema-valid request accepted, but these bodies carry
# rules JSON Schema cannot state, checked by the gateway with a 422 naming the fault:
EXCLUDED_CHECKS: dict[str, list[Any]] = {
    # any bytes are a valid `format: binary` body; a capture zip in format v1 is rarely among them
    "POST /api/v1/captures": [positive_data_acceptance],
    # one source of poses, capture_id or calibration_capture_id, poses rigid, setting names known
    "POST /api/v1/jobs": [positive_data_acceptance],
    # each pose a rigid 4x4 transform (an orthonormal block), and camera ids of one shape
    "POST /api/v1/rigs": [positive_data_acceptance],
    # poses rigid, camera ids unique, colour intrinsics and transform given together
    "POST /api/v1/streams": [positive_data_acceptance],
    # any bytes are a valid `format: binary` body; a frame-set of the stream is rarely among them
    "PUT /api/v1/streams/{stream_id}/frames/{index}": [positive_data_acceptance],
    # any bytes are a valid `format: binary` body; a well-formed preview.bin is rarely among them
    "PUT /api/v1/streams/{stream_id}/preview": [positive_data_acceptance],
    # its 503 is the readiness report, not a failure: the fixture runs no stage worker, so no
    # worker consumes the cpu and gpu queues (tests/app/test_api.py checks that answer)
    "GET /readyz": [not_a_server_error],
}


# Statuses the two data checks accept beyond schemathesis's own lists: a schema-violating body
# may be refused for its size before it is read (413), and a well-formed Range beyond the file
# is a 416 (RFC 9110), the file's size being no part of the schema.
CONFIG = SchemathesisConfig.from_dict({"checks": {
    "negative_data_rejection": {"expected-statuses": [
        "400", "401", "403", "404", "405", "406", "409", "413", "415", "422", "428", "429", "5xx"]},
    "positive_data_acceptance": {"expected-statuses": [
        "2xx", "3xx", "401", "403", "404", "409", "416", "429", "5xx"]},
}})


def _operations(service: Service) -> list[schemathesis.APIOperation]:
    schema = schemathesis.openapi.from_asgi("/openapi.json", service.client.app, config=CONFIG)
    return [result.ok() for result in schema.get_all_operations()]  # type: ignore[union-attr]


def _known_ids(service: Service) -> dict[str, str]:
    """Ids of a real capture, rig, (cancelled) job, asset and stream, so that 200s are checked
    too."""
    client, auth = service.client, service.auth
    capture = client.post("/api/v1/captures", content=service.capture_zip.read_bytes(),
                          headers={**auth, "Content-Type": "application/zip"}).json()["id"]
    eye = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0],
           [0.0, 0.0, 0.0, 1.0]]
    rig = client.post("/api/v1/rigs", headers=auth,
                      json={"name": "fuzz", "world_from_depth": {"cam0": eye}}).json()["id"]
    job = client.post("/api/v1/jobs", headers=auth, json={"capture_id": capture}).json()["id"]
    # Cancelled, so its event stream ends at once.
    assert client.delete(f"/api/v1/jobs/{job}", headers=auth).status_code == 200
    gateway = client.app.state.gateway  # type: ignore[attr-defined]
    data = b"glTF" + bytes(60)
    key = f"assets/{job}/mesh.glb"
    gateway.storage.put_bytes(key, data)
    with gateway.sessions.begin() as session:
        session.add(Asset(id=job, job_id=job, files={"mesh.glb": {
            "key": key, "sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data),
            "content_type": "model/gltf-binary"}}))
    # Receiving, with no frame-set: closing it is a 409, and it takes any frame index.
    stream = client.post("/api/v1/streams", headers=auth, json={
        "fps": 30, "depth_scale": 0.001, "cameras": [{"id": "cam0", "depth_intrinsics": {
            "width": 64, "height": 48, "fx": 60, "fy": 60, "cx": 32, "cy": 24}}]}).json()["id"]
    return {"capture_id": capture, "rig_id": rig, "job_id": job, "asset_id": job,
            "stream_id": stream}


def _strategies(operation: schemathesis.APIOperation, known: dict[str, str]
                ) -> Iterator[SearchStrategy[schemathesis.Case]]:
    yield operation.as_strategy()
    if operation.path_parameters or operation.query or operation.body:
        yield operation.as_strategy(generation_mode=GenerationMode.NEGATIVE)
    ids = {p.name: known[p.name] for p in operation.path_parameters if p.name in known}
    if ids:
        yield operation.as_strategy(path_parameters=ids)


def _keys(service: Service, case: schemathesis.Case) -> list[dict[str, str]]:
    """Headers to call a case with: the service's key in place of the bearer token the case
    was generated with, and the case as generated (a made-up key, or none). A case generated
    without the header it requires stays without it."""
    if "Authorization" in (case.headers or {}):
        return [service.auth, {}]
    return [{}]


def test_schema_covers_the_api(service: Service) -> None:
    names = {f"{op.method.upper()} {op.path}" for op in _operations(service)}
    assert {"POST /api/v1/captures", "POST /api/v1/jobs", "GET /api/v1/jobs/{job_id}",
            "DELETE /api/v1/jobs/{job_id}", "GET /api/v1/assets/{asset_id}/{name}"} <= names
    assert set(EXCLUDED_CHECKS) <= names


def _run(service: Service, strategy: SearchStrategy[schemathesis.Case],
         excluded: list[Any]) -> None:
    @given(case=strategy)
    @settings(max_examples=CONTRACT_EXAMPLES, deadline=None, database=None,
              suppress_health_check=list(HealthCheck))
    def fuzz(case: schemathesis.Case) -> None:
        for headers in _keys(service, case):
            response = case.call(headers=headers)
            case.validate_response(response, headers=headers, excluded_checks=excluded)

    fuzz()


def test_the_api_keeps_its_contract(service: Service) -> None:
    known = _known_ids(service)
    failures: dict[str, str] = {}
    for operation in _operations(service):
        for strategy in _strategies(operation, known):
            try:
                _run(service, strategy, EXCLUDED_CHECKS.get(operation.label, []))
            except Exception as exc:  # every operation's failures at once, not the first alone
                failures[operation.label] = str(exc)
    assert not failures, "\n\n".join(f"{label}:\n{text}" for label, text in failures.items())


@pytest.mark.slow
def test_no_server_errors(service: Service) -> None:
    for operation in _operations(service):
        if not_a_server_error in EXCLUDED_CHECKS.get(operation.label, []):
            continue

        @given(case=operation.as_strategy())
        @settings(max_examples=EXAMPLES_PER_OPERATION, deadline=None, database=None,
                  suppress_health_check=list(HealthCheck))
        def fuzz(case: schemathesis.Case) -> None:
            for headers in _keys(service, case):
                response = case.call(headers=headers)
                case.validate_response(response, checks=[not_a_server_error])

        fuzz()
