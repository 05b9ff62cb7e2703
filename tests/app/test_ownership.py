"""Who sees what: two keys cannot see or touch each other's captures, jobs, assets, rigs or
streams through any route; keys of one project share; an admin key sees all; share links open one
asset for anyone, until they expire."""

from __future__ import annotations

import hashlib
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest

from agent.preview import pack_preview
from app.core.security import create_key
from app.core.sharing import share_token
from tests.app.conftest import Service, admin_auth
from tests.frame_sets import frame_set, stream_body
from tests.integration.services import ANONYMOUS
from workers.models import Asset

ZIP = {"Content-Type": "application/zip"}
POSE = [[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]]


@dataclass
class Owned:
    """What key A made: a capture, a job with an asset, a rig, a stream with a frame-set."""

    capture_id: str
    job_id: str
    asset_id: str
    rig_id: str
    stream_id: str


def _key(service: Service, name: str, project: str | None = None) -> dict[str, str]:
    gateway = service.client.app.state.gateway  # type: ignore[attr-defined]
    with gateway.sessions() as session:
        _, key = create_key(session, name, project=project)
    return {"Authorization": f"Bearer {key}"}


def _unique_zip(service: Service, tag: str) -> bytes:
    """The service's capture with one more file: new content, so a capture of its own."""
    import io
    import zipfile

    buffer = io.BytesIO(service.capture_zip.read_bytes())
    with zipfile.ZipFile(buffer, "a") as archive:
        archive.writestr("notes.txt", f"{tag} {time.time_ns()}")
    return buffer.getvalue()


def _make(service: Service, auth: dict[str, str], tag: str) -> Owned:
    client = service.client
    capture = client.post("/api/v1/captures", content=_unique_zip(service, tag),
                          headers={**auth, **ZIP})
    assert capture.status_code == 201, capture.text
    rig = client.post("/api/v1/rigs", json={"world_from_depth": {"cam0": POSE}}, headers=auth)
    assert rig.status_code == 201, rig.text
    job = client.post("/api/v1/jobs", headers=auth, json={"capture_id": capture.json()["id"]})
    assert job.status_code == 202, job.text
    job_id = job.json()["id"]
    data = f"glb of {tag}".encode()
    gateway = client.app.state.gateway  # type: ignore[attr-defined]
    gateway.storage.put_bytes(f"assets/{job_id}/mesh.glb", data)
    with gateway.sessions.begin() as session:  # as a worker's export stores it
        session.add(Asset(id=job_id, job_id=job_id, files={"mesh.glb": {
            "key": f"assets/{job_id}/mesh.glb", "sha256": hashlib.sha256(data).hexdigest(),
            "bytes": len(data), "content_type": "model/gltf-binary"}}))
    stream = client.post("/api/v1/streams", json=stream_body(), headers=auth)
    assert stream.status_code == 201, stream.text
    stream_id = stream.json()["id"]
    sent = client.put(f"/api/v1/streams/{stream_id}/frames/0", content=frame_set(0),
                      headers={**auth, **ZIP})
    assert sent.status_code == 201, sent.text
    return Owned(capture.json()["id"], job_id, job_id, rig.json()["id"], stream_id)


@pytest.fixture(scope="module")
def two(service: Service) -> tuple[dict[str, str], Owned, dict[str, str], Owned]:
    a, b = _key(service, "client-a"), _key(service, "client-b")
    return a, _make(service, a, "a"), b, _make(service, b, "b")


Request = tuple[str, str, dict[str, Any]]
# Every route of the API: how key B tries it on A's things, and what B must get back.
# A list route must answer 200 without A's items.
ROUTES: dict[tuple[str, str], Callable[[Owned], Request]] = {
    ("POST", "/api/v1/captures"): lambda a: ("POST", "/api/v1/captures", {}),
    ("GET", "/api/v1/captures"): lambda a: ("GET", "/api/v1/captures?limit=100", {}),
    ("GET", "/api/v1/captures/{capture_id}"):
        lambda a: ("GET", f"/api/v1/captures/{a.capture_id}", {}),
    ("POST", "/api/v1/jobs"): lambda a: ("POST", "/api/v1/jobs",
                                         {"json": {"capture_id": a.capture_id}}),
    ("GET", "/api/v1/jobs"): lambda a: ("GET", "/api/v1/jobs?limit=100", {}),
    ("GET", "/api/v1/jobs/{job_id}"): lambda a: ("GET", f"/api/v1/jobs/{a.job_id}", {}),
    ("DELETE", "/api/v1/jobs/{job_id}"): lambda a: ("DELETE", f"/api/v1/jobs/{a.job_id}", {}),
    ("GET", "/api/v1/jobs/{job_id}/events"):
        lambda a: ("GET", f"/api/v1/jobs/{a.job_id}/events", {}),
    ("GET", "/api/v1/assets/{asset_id}"): lambda a: ("GET", f"/api/v1/assets/{a.asset_id}", {}),
    ("GET", "/api/v1/assets/{asset_id}/{name}"):
        lambda a: ("GET", f"/api/v1/assets/{a.asset_id}/mesh.glb", {}),
    ("POST", "/api/v1/assets/{asset_id}/share"):
        lambda a: ("POST", f"/api/v1/assets/{a.asset_id}/share", {"json": {}}),
    ("POST", "/api/v1/rigs"): lambda a: ("POST", "/api/v1/rigs", {}),
    ("GET", "/api/v1/rigs"): lambda a: ("GET", "/api/v1/rigs?limit=100", {}),
    ("GET", "/api/v1/rigs/{rig_id}"): lambda a: ("GET", f"/api/v1/rigs/{a.rig_id}", {}),
    ("GET", "/api/v1/rigs/{rig_id}/rig.json"):
        lambda a: ("GET", f"/api/v1/rigs/{a.rig_id}/rig.json", {}),
    ("POST", "/api/v1/streams"): lambda a: ("POST", "/api/v1/streams", {}),
    ("GET", "/api/v1/streams"): lambda a: ("GET", "/api/v1/streams?limit=100", {}),
    ("GET", "/api/v1/streams/{stream_id}"):
        lambda a: ("GET", f"/api/v1/streams/{a.stream_id}", {}),
    ("PUT", "/api/v1/streams/{stream_id}/frames/{index}"):
        lambda a: ("PUT", f"/api/v1/streams/{a.stream_id}/frames/1",
                   {"content": frame_set(1)}),
    ("POST", "/api/v1/streams/{stream_id}/close"):
        lambda a: ("POST", f"/api/v1/streams/{a.stream_id}/close", {}),
    ("PUT", "/api/v1/streams/{stream_id}/preview"):
        lambda a: ("PUT", f"/api/v1/streams/{a.stream_id}/preview",
                   {"content": pack_preview(1, time.time(), np.zeros((1, 3), np.float32),
                                            np.zeros((1, 3), np.uint8))}),
}
# Routes that make something new: B makes its own, which A then cannot see (checked below).
CREATING = {("POST", "/api/v1/captures"), ("POST", "/api/v1/rigs"), ("POST", "/api/v1/streams")}


def test_the_walk_covers_every_route(service: Service) -> None:
    paths = service.client.get("/openapi.json").json()["paths"]
    routes = {(method.upper(), path) for path, operations in paths.items()
              if path.startswith("/api/v1/") for method in operations}
    assert routes == set(ROUTES)


@pytest.mark.parametrize("route", sorted(set(ROUTES) - CREATING), ids=" ".join)
def test_another_key_sees_and_touches_nothing(service: Service, route: tuple[str, str],
                                              two: tuple[dict[str, str], Owned,
                                                         dict[str, str], Owned]) -> None:
    a_auth, a, b_auth, _ = two
    method, url, kwargs = ROUTES[route](a)
    response = service.client.request(method, url, headers=b_auth, **kwargs)
    text = response.text
    if "{" in route[1] or method == "POST":
        assert response.status_code == 404, (route, response.status_code, text)
        assert response.json()["type"].endswith("/not-found")
    else:
        assert response.status_code == 200, text
        for thing in (a.capture_id, a.job_id, a.rig_id, a.stream_id):
            assert thing not in text, (route, thing)
    # A's things are untouched and still A's.
    job = service.client.get(f"/api/v1/jobs/{a.job_id}", headers=a_auth).json()
    assert job["state"] == "queued"
    assert service.client.get(f"/api/v1/rigs/{a.rig_id}", headers=a_auth).status_code == 200
    stream = service.client.get(f"/api/v1/streams/{a.stream_id}", headers=a_auth).json()
    assert (stream["state"], stream["frames_received"]) == ("receiving", 1)


def test_what_b_makes_a_cannot_see(service: Service, two: tuple[dict[str, str], Owned,
                                                                dict[str, str], Owned]) -> None:
    a_auth, a, b_auth, b = two
    for url in (f"/api/v1/captures/{b.capture_id}", f"/api/v1/jobs/{b.job_id}",
                f"/api/v1/assets/{b.asset_id}", f"/api/v1/rigs/{b.rig_id}",
                f"/api/v1/streams/{b.stream_id}"):
        assert service.client.get(url, headers=a_auth).status_code == 404, url
        assert service.client.get(url, headers=b_auth).status_code == 200, url
    # A job of A's may not use B's rig, nor calibrate from B's capture.
    for body in ({"capture_id": a.capture_id, "rig_id": b.rig_id},
                 {"calibration_capture_id": b.capture_id}):
        response = service.client.post("/api/v1/jobs", json=body, headers=a_auth)
        assert response.status_code == 404, (body, response.text)
    # Nor may A's stream take its poses from B's rig.
    response = service.client.post("/api/v1/streams", json=stream_body(rig_id=b.rig_id),
                                   headers=a_auth)
    assert response.status_code == 404, response.text


def test_the_same_bytes_uploaded_by_two_owners(service: Service) -> None:
    first, second = _key(service, "first"), _key(service, "second")
    content = _unique_zip(service, "shared bytes")
    one = service.client.post("/api/v1/captures", content=content, headers={**first, **ZIP})
    two = service.client.post("/api/v1/captures", content=content, headers={**second, **ZIP})
    assert one.status_code == two.status_code == 201
    assert one.json()["id"] == two.json()["id"]
    # Stored once, but the second owner learns nothing of the first.
    assert "volumesh-deduplicated" not in two.headers
    again = service.client.post("/api/v1/captures", content=content, headers={**second, **ZIP})
    assert again.headers["volumesh-deduplicated"] == "true"
    for auth in (first, second):
        job = service.client.post("/api/v1/jobs", headers=auth,
                                  json={"capture_id": one.json()["id"]})
        assert job.status_code == 202, job.text
    mine = service.client.get("/api/v1/jobs?limit=100", headers=second).json()
    assert mine["total"] == 1


def test_keys_of_one_project_share_and_an_admin_sees_all(service: Service) -> None:
    one, other = _key(service, "studio 1", "studio"), _key(service, "studio 2", "studio")
    made = _make(service, one, "studio")
    for url in (f"/api/v1/captures/{made.capture_id}", f"/api/v1/jobs/{made.job_id}",
                f"/api/v1/assets/{made.asset_id}", f"/api/v1/rigs/{made.rig_id}",
                f"/api/v1/streams/{made.stream_id}"):
        assert service.client.get(url, headers=other).status_code == 200, url
        assert service.client.get(url, headers=admin_auth(service)).status_code == 200, url
        assert service.client.get(url, headers=_key(service, "outsider")).status_code == 404
    cancelled = service.client.delete(f"/api/v1/jobs/{made.job_id}", headers=other)
    assert cancelled.status_code == 200 and cancelled.json()["state"] == "cancelled"
    listed = service.client.get("/api/v1/jobs?limit=100", headers=admin_auth(service)).json()
    assert made.job_id in {job["id"] for job in listed["items"]}


def test_a_share_link_opens_one_asset_for_anyone_until_it_expires(
        service: Service, two: tuple[dict[str, str], Owned, dict[str, str], Owned]) -> None:
    a_auth, a, b_auth, b = two
    link = service.client.post(f"/api/v1/assets/{a.asset_id}/share", headers=a_auth,
                               json={"expires_in_s": 600})
    assert link.status_code == 201, link.text
    shared = link.json()
    assert shared["viewer_url"] == f"/?asset={a.asset_id}&share={shared['share']}"
    mesh = service.client.get(shared["files"]["mesh.glb"], headers=ANONYMOUS)
    assert mesh.status_code == 200 and mesh.content == b"glb of a"
    assert "private" in mesh.headers["cache-control"]
    listing = service.client.get(f"/api/v1/assets/{a.asset_id}?share={shared['share']}",
                                 headers=ANONYMOUS).json()
    assert listing["files"]["mesh.glb"]["url"] == shared["files"]["mesh.glb"]
    # Another key holder opens it too (the viewer sends its own key along).
    assert service.client.get(shared["files"]["mesh.glb"], headers=b_auth).status_code == 200
    # The token opens that asset alone, and nothing else.
    other = service.client.get(f"/api/v1/assets/{b.asset_id}/mesh.glb?share={shared['share']}",
                               headers=ANONYMOUS)
    assert other.status_code == 401
    assert service.client.get(f"/api/v1/jobs/{a.job_id}?share={shared['share']}",
                              headers=ANONYMOUS).status_code == 401
    secret = service.client.app.state.gateway.share_secret  # type: ignore[attr-defined]
    expired = share_token(secret, a.asset_id, int(time.time()) - 1)
    tampered = share_token(secret, a.asset_id, int(time.time()) + 60)[:-2] + "AA"
    for token in (expired, tampered, share_token(b"\0" * 32, a.asset_id, 2_000_000_000)):
        response = service.client.get(f"/api/v1/assets/{a.asset_id}/mesh.glb?share={token}",
                                      headers=ANONYMOUS)
        assert response.status_code == 401, token
        assert "share link" in response.json()["detail"]
    too_long = service.client.post(f"/api/v1/assets/{a.asset_id}/share", headers=a_auth,
                                   json={"expires_in_s": 90 * 24 * 3600})
    assert too_long.status_code == 422


def test_another_key_reaches_no_sequence_nor_its_frames(
        service: Service, two: tuple[dict[str, str], Owned, dict[str, str], Owned]) -> None:
    a_auth, a, b_auth, _ = two
    sequence = service.client.post("/api/v1/jobs", headers=a_auth,
                                   json={"capture_id": a.capture_id, "frames": "all"})
    assert sequence.status_code == 202, sequence.text
    sequence_id = sequence.json()["id"]
    frames = service.client.get(f"/api/v1/jobs?parent_id={sequence_id}", headers=a_auth).json()
    assert frames["total"] == 1
    frame_id = frames["items"][0]["id"]
    for auth, total in ((b_auth, 0), (a_auth, 1)):  # frames inherit their sequence's owner
        listed = service.client.get(f"/api/v1/jobs?parent_id={sequence_id}", headers=auth)
        assert listed.status_code == 200 and listed.json()["total"] == total
    for url in (f"/api/v1/jobs/{sequence_id}", f"/api/v1/jobs/{frame_id}"):
        assert service.client.get(url, headers=b_auth).status_code == 404, url
        assert service.client.delete(url, headers=b_auth).status_code == 404, url
        assert service.client.get(url, headers=a_auth).json()["state"] == "queued"
    cancelled = service.client.delete(f"/api/v1/jobs/{sequence_id}", headers=a_auth)
    assert cancelled.status_code == 200
