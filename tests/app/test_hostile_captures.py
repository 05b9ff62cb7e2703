"""Captures built to crash or exhaust the validator, uploaded to the real gateway with a real
validation worker: each is refused within seconds with a 422 naming the file, nothing of it is
kept, and a job on it is a clear 404. An upload no worker validates ends with nothing kept."""

from __future__ import annotations

import hashlib
import io
import time
import zipfile
from pathlib import Path
from typing import Any

import pytest

from tests.app.conftest import Service
from tests.hostile_captures import (
    BOMB_MEMBER,
    bomb_capture_zip,
    damaged_member_zip,
    padded_png,
)
from tests.integration.services import gateway_client

ZIP = {"Content-Type": "application/zip"}
PROBLEM = "application/problem+json"


def _entries(service: Service) -> dict[str, bytes]:
    with zipfile.ZipFile(service.capture_zip) as archive:
        return {name: archive.read(name) for name in archive.namelist()}


def _damaged(service: Service, how: str) -> tuple[bytes, str]:
    member = "cam1/depth/000000.png"
    entries = _entries(service)
    # Long enough that the damage lies past what opening the capture reads of it.
    entries[member] = padded_png(entries[member], 200_000)
    return damaged_member_zip(entries, member, how), member


HOSTILE = {
    "member with a bad CRC": lambda s: _damaged(s, "crc"),
    "member with broken deflate": lambda s: _damaged(s, "deflate"),
    "member whose data end early": lambda s: _damaged(s, "truncate"),
    "12000x12000 16-bit PNG bomb": lambda s: (bomb_capture_zip(), BOMB_MEMBER),
}


def _assert_nothing_kept(client: Any, data_dir: Path, body: bytes,
                         auth: dict[str, str]) -> None:
    sha256 = hashlib.sha256(body).hexdigest()
    assert not list(data_dir.rglob(f"{sha256}*.zip")), "the refused zip was kept"
    assert not list((data_dir / "tmp").glob("upload-*"))
    assert client.get(f"/api/v1/captures/{sha256[:32]}", headers=auth).status_code == 404
    job = client.post("/api/v1/jobs", json={"capture_id": sha256[:32]}, headers=auth)
    assert job.status_code == 404 and job.headers["content-type"].startswith(PROBLEM)
    assert "upload it with POST /api/v1/captures" in job.json()["detail"]


@pytest.mark.parametrize("name", sorted(HOSTILE))
def test_a_hostile_capture_is_refused_within_seconds_naming_the_file(
        service: Service, name: str) -> None:
    body, member = HOSTILE[name](service)
    if name.startswith("12000"):
        assert len(body) < 300_000  # small on the wire, 288 MB decoded
    started = time.monotonic()
    response = service.client.post("/api/v1/captures", content=body,
                                   headers={**service.auth, **ZIP})
    assert time.monotonic() - started < 10.0
    assert response.status_code == 422, response.text
    assert response.headers["content-type"].startswith(PROBLEM)
    problem = response.json()
    assert problem["type"].endswith("/invalid-capture")
    assert member in problem["detail"] or "capture.json: cameras[0].depth_intrinsics: " \
        "12000x12000 is 144000000 pixels" in problem["detail"], problem["detail"]
    _assert_nothing_kept(service.client, service.data_dir, body, service.auth)


def test_the_worker_survives_them_and_still_accepts_a_valid_capture(service: Service) -> None:
    for name in sorted(HOSTILE):
        body, _ = HOSTILE[name](service)
        service.client.post("/api/v1/captures", content=body, headers={**service.auth, **ZIP})
    assert service.worker.alive
    response = service.client.post("/api/v1/captures", content=service.capture_zip.read_bytes(),
                                   headers={**service.auth, **ZIP})
    assert response.status_code == 201, response.text


def test_a_finished_capture_is_never_forgotten_by_a_timed_out_wait(service: Service) -> None:
    from app.core.capture_store import forget

    body = service.capture_zip.read_bytes()
    response = service.client.post("/api/v1/captures", content=body,
                                   headers={**service.auth, **ZIP})
    assert response.status_code == 201
    gateway = service.client.app.state.gateway  # type: ignore[attr-defined]
    assert not forget(gateway, response.json()["id"], "validating")
    assert service.client.get(f"/api/v1/captures/{response.json()['id']}").status_code == 200


def test_an_upload_no_worker_validates_ends_with_nothing_kept(tmp_path: Path,
                                                              small_capture_zip: Path) -> None:
    values = {"data_dir": str(tmp_path), "validation_timeout_s": "1"}
    body = small_capture_zip.read_bytes()
    with gateway_client(values) as (client, auth):  # no worker at all
        for _ in range(2):  # and the same upload again is not stuck behind the first
            response = client.post("/api/v1/captures", content=body, headers={**auth, **ZIP})
            assert response.status_code == 503, response.text
            problem = response.json()
            assert problem["type"].endswith("/validation-timeout")
            assert "was not kept; upload it again later" in problem["detail"]
            assert response.headers["retry-after"] == "30"
            _assert_nothing_kept(client, tmp_path, body, auth)


def test_hostile_builders_make_what_they_say() -> None:
    with zipfile.ZipFile(io.BytesIO(bomb_capture_zip())) as archive:
        assert archive.testzip() is None
        assert archive.getinfo(BOMB_MEMBER).file_size < 300_000
