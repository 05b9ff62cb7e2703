"""Streams through the real gateway and a real validate worker: frame-sets stored once per
index, malformed ones refused naming the entry, and a closed stream assembled into a capture
that jobs take like an upload."""

from __future__ import annotations

import io
import json
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from app.core.security import create_key
from tests.app.conftest import Service
from tests.frame_sets import (
    CAMERAS,
    color_jpeg,
    depth_png,
    frame_entries,
    frame_set,
    pack,
    stream_body,
)
from tests.integration.services import gateway_client
from workers.models import Capture

ZIP = {"Content-Type": "application/zip"}
POSE = [[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0.5], [0, 0, 0, 1.0]]


def _create(service: Service, **extra: Any) -> dict[str, Any]:
    created = service.client.post("/api/v1/streams", json=stream_body(**extra))
    assert created.status_code == 201, created.text
    return dict(created.json())


def _put(service: Service, stream_id: str, index: int, body: bytes,
         timestamp_us: int = 0, **headers: str) -> Any:
    return service.client.put(f"/api/v1/streams/{stream_id}/frames/{index}", content=body,
                              headers={**ZIP, "Volumesh-Timestamp-Us": str(timestamp_us),
                                       **headers})


def _wait_over(service: Service, stream_id: str, timeout_s: float = 60) -> dict[str, Any]:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        stream = service.client.get(f"/api/v1/streams/{stream_id}").json()
        if stream["state"] in ("closed", "failed"):
            return dict(stream)
        time.sleep(0.1)
    raise AssertionError(f"stream {stream_id} still {stream['state']}\n{service.worker.tail()}")


def _stored_capture(service: Service, capture_id: str) -> zipfile.ZipFile:
    gateway = service.client.app.state.gateway  # type: ignore[attr-defined]
    with gateway.sessions() as session:
        row = session.get(Capture, capture_id)
        assert row is not None
        path = gateway.storage.local_path(row.storage_key)
    assert path is not None
    return zipfile.ZipFile(io.BytesIO(path.read_bytes()))


def _chunks(service: Service, stream_id: str) -> list[str]:
    folder = service.data_dir / "storage" / "streams" / stream_id
    return sorted(p.name for p in folder.glob("*.zip")) if folder.is_dir() else []


def test_a_stream_stores_each_frame_set_once_and_assembles_a_capture(service: Service) -> None:
    stream = _create(service)
    sid = stream["id"]
    assert stream["state"] == "receiving" and stream["frames_received"] == 0
    assert stream["preview_url"] == f"/api/v1/streams/{sid}/preview"
    for index in (2, 0, 1):  # out of order, as retries deliver them
        body = frame_set(index, color=index == 1)
        sent = _put(service, sid, index, body, timestamp_us=1_000_000 + 33_333 * index)
        assert sent.status_code == 201, sent.text
        assert sent.json()["stored"] is True
    again = _put(service, sid, 1, frame_set(1), timestamp_us=5)
    assert again.status_code == 200, again.text
    assert again.json() == {"stream_id": sid, "index": 1, "stored": False, "frames_received": 3}
    shown = service.client.get(f"/api/v1/streams/{sid}").json()
    assert (shown["frames_received"], shown["last_frame_index"]) == (3, 2)
    assert _chunks(service, sid) == ["000000.zip", "000001.zip", "000002.zip"]

    closing = service.client.post(f"/api/v1/streams/{sid}/close")
    assert closing.status_code == 202, closing.text
    assert closing.json()["state"] == "assembling"
    assert service.client.post(f"/api/v1/streams/{sid}/close").status_code == 200
    late = _put(service, sid, 3, frame_set(3))
    assert late.status_code == 409 and late.json()["type"].endswith("/stream-not-receiving")
    assert _put(service, sid, 0, frame_set(0)).json()["stored"] is False  # still acknowledged

    closed = _wait_over(service, sid)
    assert closed["state"] == "closed", closed["error"]
    capture = service.client.get(f"/api/v1/captures/{closed['capture_id']}").json()
    assert (capture["state"], capture["cameras"], capture["frames"]) == ("ready", 2, 3)
    with _stored_capture(service, closed["capture_id"]) as archive:
        names = archive.namelist()
        document = json.loads(archive.read("capture.json"))
        assert names[0] == "capture.json"
        assert {i.compress_type for i in archive.infolist()} == {zipfile.ZIP_STORED}
        assert archive.read("cam1/depth/000002.png") == depth_png(2)
    assert document["frames"] == [{"index": i, "timestamp_us": 1_000_000 + 33_333 * i}
                                  for i in range(3)]
    assert "cam0/color/000001.jpg" in names
    assert [c["id"] for c in document["cameras"]] == list(CAMERAS)
    assert _chunks(service, sid) == []

    job = service.client.post("/api/v1/jobs", json={"capture_id": closed["capture_id"],
                                                    "frames": "all"})
    assert job.status_code == 202, job.text
    assert job.json()["frames_total"] == 3
    assert service.client.delete(f"/api/v1/jobs/{job.json()['id']}").status_code == 200
    listed = service.client.get("/api/v1/streams?state=closed&limit=100").json()
    assert sid in {s["id"] for s in listed["items"]}
    receiving = service.client.get("/api/v1/streams?state=receiving&limit=100").json()
    assert sid not in {s["id"] for s in receiving["items"]}


def _eight_bit(entries: dict[str, bytes]) -> dict[str, bytes]:
    entries["cam0/depth/000000.png"] = depth_png(0, dtype=np.uint8)
    return entries


def _resized(entries: dict[str, bytes]) -> dict[str, bytes]:
    entries["cam1/depth/000000.png"] = depth_png(0, width=32)
    return entries


def _bad_checksum(entries: dict[str, bytes]) -> dict[str, bytes]:
    png = entries["cam0/depth/000000.png"]
    entries["cam0/depth/000000.png"] = png[:30] + bytes([png[30] ^ 0xFF]) + png[31:]
    return entries


def _png_colour(entries: dict[str, bytes]) -> dict[str, bytes]:
    entries["cam0/color/000000.png"] = color_jpeg()
    return entries


@pytest.mark.parametrize(("malformed", "names"), [
    (lambda e: {k: v for k, v in e.items() if not k.startswith("cam1/")},
     "cam1/depth/000000.png"),
    (_resized, "cam1/depth/000000.png"),
    (_eight_bit, "cam0/depth/000000.png"),
    (_bad_checksum, "'cam0/depth/000000.png' is damaged"),
    (lambda e: {**e, "notes.txt": b"hello"}, "notes.txt"),
    (lambda e: {**e, "preview.bin": b"\x02\x00\x00\x00{}"}, "PUT /streams/{id}/preview"),
    (lambda e: {**e, "cam0/depth/000001.png": depth_png(1)}, "cam0/depth/000001.png"),
    (_png_colour, "cam0/color/000000.png"),
    (None, "not a readable zip"),
], ids=["missing camera", "wrong size", "8-bit", "damaged header", "extra entry",
        "a preview inside", "other index", "not a PNG", "not a zip"])
def test_a_malformed_frame_set_is_refused_naming_the_entry(service: Service, malformed: Any,
                                                           names: str) -> None:
    sid = _create(service)["id"]
    body = b"PK\x03\x04 not really" if malformed is None else pack(malformed(frame_entries(0)))
    refused = _put(service, sid, 0, body)
    assert refused.status_code == 422, refused.text
    assert refused.json()["type"].endswith("/invalid-frame-set")
    assert names in refused.json()["detail"]
    assert service.client.get(f"/api/v1/streams/{sid}").json()["frames_received"] == 0
    assert _chunks(service, sid) == []


def test_what_a_frame_set_request_needs(service: Service) -> None:
    sid = _create(service)["id"]
    body = frame_set(0)
    wrong_type = _put(service, sid, 0, body, **{"Content-Type": "application/json"})
    assert wrong_type.status_code == 415
    assert _put(service, sid, 0, body, timestamp_us=-1).status_code == 422
    assert _put(service, sid, 1_000_000, body).status_code == 422
    unknown = _put(service, "0" * 32, 0, body)
    assert unknown.status_code == 404 and unknown.json()["type"].endswith("/not-found")
    empty = service.client.post(f"/api/v1/streams/{sid}/close")
    assert empty.status_code == 409 and empty.json()["type"].endswith("/stream-empty")


def test_a_frame_set_over_the_limit_is_a_413(tmp_path: Path) -> None:
    body = frame_set(0)
    values = {"data_dir": str(tmp_path), "max_frame_set_bytes": str(len(body) - 1)}
    with gateway_client(values) as (client, _):  # no worker: nothing is assembled
        sid = client.post("/api/v1/streams", json=stream_body()).json()["id"]
        url = f"/api/v1/streams/{sid}/frames/0"
        declared = client.put(url, content=body, headers=ZIP)
        assert declared.status_code == 413, declared.text

        def chunked() -> Iterator[bytes]:  # no Content-Length: counted as it arrives
            yield body[:100]
            yield body[100:]

        streamed = client.put(url, content=chunked(), headers=ZIP)
        assert streamed.status_code == 413, streamed.text
        assert client.get(f"/api/v1/streams/{sid}").json()["frames_received"] == 0
        at_limit = client.put(url, content=body[:-1], headers=ZIP)  # read whole: cut short
        assert at_limit.status_code == 422, at_limit.text


@pytest.mark.parametrize(("change", "says"), [
    ({"fps": 0}, "fps"),
    ({"cameras": []}, "cameras"),
    ({"cameras": [{"id": "cam0", "depth_intrinsics": {"width": 64, "height": 48, "fx": 0,
                                                       "fy": 60, "cx": 32, "cy": 24}}]}, "fx"),
    ({"cameras": [{"id": "a b", "depth_intrinsics": {"width": 64, "height": 48, "fx": 60,
                                                      "fy": 60, "cx": 32, "cy": 24}}]}, "id"),
    ({"cameras": [stream_body()["cameras"][0]] * 2}, "camera ids repeat: cam0"),
    ({"cameras": [{**stream_body()["cameras"][0], "world_from_depth": [[2, 0, 0, 0]] * 3
                   + [[0, 0, 0, 1]]}]}, "camera cam0: world_from_depth: is not rigid"),
    ({"cameras": [{**stream_body()["cameras"][0],
                   "color_intrinsics": stream_body()["cameras"][0]["depth_intrinsics"]}]},
     "color_intrinsics and color_from_depth"),
])
def test_a_bad_stream_is_refused_naming_the_field(service: Service, change: dict[str, Any],
                                                  says: str) -> None:
    refused = service.client.post("/api/v1/streams", json={**stream_body(), **change})
    assert refused.status_code == 422, refused.text
    assert says in refused.json()["detail"]


def test_a_rig_gives_the_cameras_their_poses(service: Service) -> None:
    rig = service.client.post("/api/v1/rigs", json={"world_from_depth": {
        "cam0": POSE, "cam1": POSE}}).json()["id"]
    stream = _create(service, rig_id=rig)
    assert [c["world_from_depth"] for c in stream["cameras"]] == [POSE, POSE]
    assert service.client.get(f"/api/v1/streams/{stream['id']}").json()["cameras"] == \
        stream["cameras"]
    partial = service.client.post("/api/v1/rigs", json={"world_from_depth": {"cam0": POSE}})
    lacking = service.client.post("/api/v1/streams",
                                  json=stream_body(rig_id=partial.json()["id"]))
    assert lacking.status_code == 422 and "camera cam1" in lacking.json()["detail"]


def test_another_owner_reaches_no_stream(service: Service) -> None:
    gateway = service.client.app.state.gateway  # type: ignore[attr-defined]
    with gateway.sessions() as session:
        _, key = create_key(session, "stranger")
    other = {"Authorization": f"Bearer {key}"}
    sid = _create(service)["id"]
    assert _put(service, sid, 0, frame_set(0)).status_code == 201
    for method, url, kwargs in (
            ("GET", f"/api/v1/streams/{sid}", {}),
            ("PUT", f"/api/v1/streams/{sid}/frames/1", {"content": frame_set(1)}),
            ("POST", f"/api/v1/streams/{sid}/close", {})):
        answer = service.client.request(method, url, headers={**other, **ZIP}, **kwargs)
        assert answer.status_code == 404, (method, url, answer.text)
    assert service.client.get("/api/v1/streams", headers=other).json()["total"] == 0
    mine = service.client.get(f"/api/v1/streams/{sid}").json()
    assert (mine["state"], mine["frames_received"]) == ("receiving", 1)
