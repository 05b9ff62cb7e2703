"""The REST API against the in-process gateway: captures, jobs (queued, listed, cancelled,
events), assets (ETag, Range, caching), health, metrics and the OpenAPI document."""

from __future__ import annotations

import hashlib
import json
import os

from pydantic import SecretStr

from tests.app.conftest import Service, admin_auth
from tests.integration.services import ANONYMOUS
from workers.models import Asset, Job

ZIP = {"Content-Type": "application/zip"}


def upload(service: Service) -> dict[str, object]:
    response = service.client.post("/api/v1/captures", content=service.capture_zip.read_bytes(),
                                   headers={**service.auth, **ZIP})
    assert response.status_code == 201, response.text
    return response.json()


def test_upload_is_stored_once_and_listed(service: Service) -> None:
    first = upload(service)
    assert (first["cameras"], first["frames"], first["state"]) == (2, 1, "ready")
    assert first["bytes"] == service.capture_zip.stat().st_size
    assert first["sha256"] == hashlib.sha256(service.capture_zip.read_bytes()).hexdigest()
    files = service.client.post("/api/v1/captures", headers=service.auth, files={
        "file": ("capture.zip", service.capture_zip.read_bytes(), "application/zip")})
    assert files.status_code == 201 and files.json()["id"] == first["id"]
    assert files.headers["volumesh-deduplicated"] == "true"
    assert files.headers["location"] == f"/api/v1/captures/{first['id']}"
    stored = list((service.data_dir / "storage" / "captures").glob(f"{first['sha256']}*"))
    assert len(stored) == 1
    got = service.client.get(f"/api/v1/captures/{first['id']}").json()
    assert got == first
    listed = service.client.get("/api/v1/captures?limit=100").json()
    assert first["id"] in [c["id"] for c in listed["items"]]


def test_job_is_queued_listed_cancelled_and_streamed(service: Service) -> None:
    capture = upload(service)
    response = service.client.post("/api/v1/jobs", headers=service.auth, json={
        "capture_id": capture["id"], "enhance": False, "draco_position_bits": 12})
    assert response.status_code == 202, response.text
    job = response.json()
    assert response.headers["location"] == f"/api/v1/jobs/{job['id']}"
    assert job["state"] == "queued" and job["progress"] == 0.0
    assert job["options"] == {"enhance": False, "draco_position_bits": 12}
    assert service.client.get(f"/api/v1/jobs/{job['id']}").json()["id"] == job["id"]
    page = service.client.get("/api/v1/jobs", params={"state": "queued", "limit": 1}).json()
    assert page["limit"] == 1 and page["total"] >= 1 and len(page["items"]) == 1
    by_capture = service.client.get("/api/v1/jobs", params={"capture_id": capture["id"]}).json()
    assert job["id"] in [j["id"] for j in by_capture["items"]]

    cancelled = service.client.delete(f"/api/v1/jobs/{job['id']}", headers=service.auth)
    assert cancelled.status_code == 200 and cancelled.json()["state"] == "cancelled"
    again = service.client.delete(f"/api/v1/jobs/{job['id']}", headers=service.auth)
    assert again.status_code == 200 and again.json()["state"] == "cancelled"

    with service.client.stream("GET", f"/api/v1/jobs/{job['id']}/events") as events:
        assert events.headers["content-type"].startswith("text/event-stream")
        text = "".join(events.iter_text())
    data = [json.loads(line[6:]) for line in text.splitlines() if line.startswith("data: ")]
    assert data and data[-1]["state"] == "cancelled"  # the stream ends with the final state


def test_finished_job_cannot_be_cancelled(service: Service) -> None:
    capture = upload(service)
    job = service.client.post("/api/v1/jobs", headers=service.auth,
                              json={"capture_id": capture["id"]}).json()
    gateway = service.client.app.state.gateway  # type: ignore[attr-defined]
    with gateway.sessions.begin() as session:
        row = session.get(Job, job["id"])
        row.state = "failed"
    response = service.client.delete(f"/api/v1/jobs/{job['id']}", headers=service.auth)
    assert response.status_code == 409
    assert "already failed" in response.json()["detail"]


def _asset(service: Service, data: bytes) -> str:
    """An asset row and its stored file, as a worker's export writes them."""
    capture = upload(service)
    job = service.client.post("/api/v1/jobs", headers=service.auth,
                              json={"capture_id": capture["id"]}).json()
    gateway = service.client.app.state.gateway  # type: ignore[attr-defined]
    key = f"assets/{job['id']}/mesh.glb"
    gateway.storage.put_bytes(key, data)
    files = {"mesh.glb": {"key": key, "sha256": hashlib.sha256(data).hexdigest(),
                          "bytes": len(data), "content_type": "model/gltf-binary"}}
    with gateway.sessions.begin() as session:
        session.add(Asset(id=job["id"], job_id=job["id"], files=files))
    return str(job["id"])


def test_asset_caching_and_ranges(service: Service) -> None:
    data = os.urandom(200_000)
    asset_id = _asset(service, data)
    url = f"/api/v1/assets/{asset_id}/mesh.glb"
    whole = service.client.get(url)
    assert whole.status_code == 200 and whole.content == data
    etag = whole.headers["etag"]
    assert etag == f'"{hashlib.sha256(data).hexdigest()}"'
    assert "immutable" in whole.headers["cache-control"]
    assert whole.headers["content-type"] == "model/gltf-binary"
    assert whole.headers["accept-ranges"] == "bytes"
    assert service.client.get(url, headers={"If-None-Match": etag}).status_code == 304
    part = service.client.get(url, headers={"Range": "bytes=100-1099"})
    assert part.status_code == 206 and part.content == data[100:1100]
    assert part.headers["content-range"] == f"bytes 100-1099/{len(data)}"
    tail = service.client.get(url, headers={"Range": "bytes=-500"})
    assert tail.status_code == 206 and tail.content == data[-500:]
    open_end = service.client.get(url, headers={"Range": "bytes=199000-"})
    assert open_end.content == data[199000:]
    stale = service.client.get(url, headers={"Range": "bytes=0-9", "If-Range": '"other"'})
    assert stale.status_code == 200 and len(stale.content) == len(data)
    outside = service.client.get(url, headers={"Range": "bytes=300000-"})
    assert outside.status_code == 416
    assert outside.headers["content-range"] == f"bytes */{len(data)}"
    head = service.client.head(url)
    assert head.status_code == 200 and head.headers["content-length"] == str(len(data))
    listing = service.client.get(f"/api/v1/assets/{asset_id}").json()
    assert listing["files"]["mesh.glb"]["url"] == url
    assert service.client.get(f"/api/v1/assets/{asset_id}/mesh.ply").status_code == 404


def test_health_readiness_metrics_and_docs(service: Service) -> None:
    assert service.client.get("/healthz").json() == {"status": "ok", "checks": {}}
    ready = service.client.get("/readyz")  # the service's one worker only validates uploads
    assert ready.status_code == 503 and ready.json() == {"status": "unavailable", "checks": {
        "database": "ok", "storage": "ok", "broker": "ok",
        "queues": "no live worker consumes cpu, gpu"}}
    metrics = service.client.get("/metrics", headers=admin_auth(service)).text
    assert 'volumesh_http_requests_total{method="GET",route="/healthz",status="200"}' in metrics
    assert "volumesh_jobs{state=" in metrics
    schema = service.client.get("/openapi.json").json()
    assert "/api/v1/jobs/{job_id}" in schema["paths"]
    assert service.client.get("/docs").status_code == 200


def test_reads_need_a_key(service: Service) -> None:
    for path in ("/api/v1/jobs", "/api/v1/captures", "/api/v1/rigs", "/metrics"):
        response = service.client.get(path, headers=ANONYMOUS)
        assert response.status_code == 401, path
        assert response.headers["www-authenticate"].startswith("Bearer")
    assert service.client.get("/healthz", headers=ANONYMOUS).status_code == 200
    assert "checks" in service.client.get("/readyz", headers=ANONYMOUS).json()


def test_metrics_take_their_token_or_an_admin_key(service: Service) -> None:
    from fastapi.testclient import TestClient

    from app.main import create_app

    token = "metrics-" + "x" * 30
    settings = service.settings.model_copy(update={"metrics_token": SecretStr(token)})
    with TestClient(create_app(settings, viewer=False)) as client:
        scraped = client.get("/metrics", headers={"Authorization": f"Bearer {token}"})
        assert scraped.status_code == 200 and "volumesh_http_requests_total" in scraped.text
        assert client.get("/metrics", headers=service.auth).status_code == 403  # not an admin
        assert client.get("/metrics", headers=admin_auth(service)).status_code == 200
        wrong = client.get("/metrics", headers={"Authorization": f"Bearer {token}x"})
        assert wrong.status_code == 401
        # The metrics token is no API key.
        assert client.get("/api/v1/jobs", headers={"Authorization": f"Bearer {token}"}
                          ).status_code == 401


def test_cors_is_configurable(service: Service) -> None:
    from fastapi.testclient import TestClient

    from app.main import create_app

    settings = service.settings.model_copy(update={"cors_origins": ["https://viewer.example"]})
    with TestClient(create_app(settings, viewer=False)) as client:
        response = client.get("/api/v1/jobs", headers={"Origin": "https://viewer.example"})
        assert response.headers["access-control-allow-origin"] == "https://viewer.example"
        other = client.get("/api/v1/jobs", headers={"Origin": "https://evil.example"})
        assert "access-control-allow-origin" not in other.headers


def test_readiness_reports_an_unreachable_broker(service: Service) -> None:
    from fastapi.testclient import TestClient

    from app.main import create_app
    from tests.integration.services import free_port

    settings = service.settings.model_copy(
        update={"broker_url": f"redis://127.0.0.1:{free_port()}/0"})
    with TestClient(create_app(settings, viewer=False)) as client:
        response = client.get("/readyz")
        assert response.status_code == 503
        body = response.json()
        assert body["status"] == "unavailable"
        assert body["checks"]["broker"].startswith("unreachable")
        assert body["checks"]["database"] == "ok"
        # Without a broker a job cannot be queued: a clear 503, not a 500.
        capture = upload(service)
        before = client.get("/api/v1/jobs", headers=service.auth).json()["total"]
        job = client.post("/api/v1/jobs", headers=service.auth,
                          json={"capture_id": capture["id"]})
        assert job.status_code == 503, job.text
        assert "broker" in job.json()["detail"]
        assert job.headers["retry-after"]
        # No job was left behind to wait forever for a task that was never queued.
        assert client.get("/api/v1/jobs", headers=service.auth).json()["total"] == before
        # A new upload cannot be validated either: 503, and nothing half-accepted is kept.
        fresh = service.client.post("/api/v1/captures", headers=service.auth, files={
            "file": ("c.zip", _with_extra_file(service.capture_zip.read_bytes()),
                     "application/zip")})
        assert fresh.status_code == 201  # the real gateway (its broker is up) still works
        content = _with_extra_file(service.capture_zip.read_bytes(), name="other.txt")
        down = client.post("/api/v1/captures", content=content,
                           headers={**service.auth, **ZIP})
        assert down.status_code == 503, down.text
        sha = hashlib.sha256(content).hexdigest()
        assert client.get(f"/api/v1/captures/{sha[:32]}", headers=service.auth).status_code == 404
        assert not list((service.data_dir / "storage" / "captures").glob(f"{sha}*"))


def _with_extra_file(data: bytes, name: str = "notes.txt") -> bytes:
    """The same capture with one more file: different bytes, still a valid capture."""
    import io
    import zipfile

    buffer = io.BytesIO(data)
    with zipfile.ZipFile(buffer, "a") as archive:
        archive.writestr(name, b"extra")
    return buffer.getvalue()
