"""Housekeeping against real gateways: the upload byte counter, the stalled-body timeout, the
sweep of stale partial uploads while the gateway runs, and the retention sweep."""

from __future__ import annotations

import json
import os
import re
import socket
import time
from pathlib import Path
from typing import Any

from tests.app.conftest import Service, admin_auth
from tests.integration.services import (
    Gateway,
    base_env,
    create_key,
    gateway_client,
    wait_for,
)

ZIP = {"Content-Type": "application/zip"}


def _uploaded_bytes(service: Service) -> float:
    text = service.client.get("/metrics", headers=admin_auth(service)).text
    found = re.search(r"^volumesh_upload_bytes_total (\S+)$", text, re.MULTILINE)
    assert found, text
    return float(found.group(1))


def test_accepted_uploads_count_their_bytes(service: Service) -> None:
    size = service.capture_zip.stat().st_size
    before = _uploaded_bytes(service)
    raw = service.client.post("/api/v1/captures", content=service.capture_zip.read_bytes(),
                              headers={**service.auth, **ZIP})
    assert raw.status_code == 201, raw.text
    assert _uploaded_bytes(service) == before + size
    # A multipart upload counts the zip, not the form around it.
    form = service.client.post("/api/v1/captures", headers=service.auth, files={
        "file": ("capture.zip", service.capture_zip.read_bytes(), "application/zip")})
    assert form.status_code == 201, form.text
    assert _uploaded_bytes(service) == before + 2 * size
    # A refused upload (not a zip) is received whole but not counted.
    refused = service.client.post("/api/v1/captures", content=b"not a zip" * 100,
                                  headers={**service.auth, **ZIP})
    assert refused.status_code in (400, 422), refused.text
    assert _uploaded_bytes(service) == before + 2 * size


def _read_answer(sock: socket.socket) -> bytes:
    answer = b""
    while chunk := sock.recv(65536):  # the gateway closes the connection after its answer
        answer += chunk
    return answer


def test_a_stalled_upload_is_answered_408_and_its_part_removed(tmp_path: Path) -> None:
    data_dir = tmp_path / "data"
    env = base_env(data_dir=str(data_dir), upload_idle_timeout_s="1.5",
                   embedded_worker="false")
    key = create_key(env)
    gateway = Gateway(env, tmp_path / "gateway.log").start()
    try:
        with socket.create_connection(("127.0.0.1", gateway.port), timeout=20) as sock:
            sock.sendall(b"POST /api/v1/captures HTTP/1.1\r\nHost: test\r\n"
                         b"Authorization: Bearer " + key.encode() + b"\r\n"
                         b"Content-Type: application/zip\r\n"
                         b"Content-Length: 2000000000\r\n\r\n" + b"PK\x03\x04" + bytes(96))
            parts = wait_for(lambda: list((data_dir / "tmp").glob("upload-*.part")), 10,
                             "the partial upload to be written")
            started = time.monotonic()
            answer = _read_answer(sock)
            waited = time.monotonic() - started
        head, _, body = answer.partition(b"\r\n\r\n")
        assert head.startswith(b"HTTP/1.1 408"), answer[:500]
        assert b"content-type: application/problem+json" in head.lower()
        assert json.loads(body)["type"].endswith("/body-timeout")
        assert waited < 10
        assert not parts[0].exists()
        assert not list((data_dir / "tmp").glob("upload-*.part"))
        assert "Traceback" not in gateway.log.read_text(errors="replace")
    finally:
        gateway.stop()


def test_stale_partial_uploads_are_swept_while_the_gateway_runs(tmp_path: Path) -> None:
    values = {"data_dir": str(tmp_path / "data"), "stale_upload_s": "2"}
    with gateway_client(values) as (client, _):
        tmp = tmp_path / "data" / "tmp"
        tmp.mkdir(parents=True, exist_ok=True)
        stale, fresh = tmp / "upload-stale.part", tmp / "upload-fresh.part"
        stale.write_bytes(b"left by a gateway that died")
        old = time.time() - 60
        os.utime(stale, (old, old))
        fresh.write_bytes(b"being written")
        wait_for(lambda: not stale.exists(), 10, "the stale partial upload to be swept")
        assert fresh.exists()  # younger than VOLUMESH_STALE_UPLOAD_S: a live upload's file
        assert client.get("/healthz").status_code == 200


def test_the_gateway_deletes_what_outlived_the_retention(tmp_path: Path) -> None:
    from datetime import timedelta

    from workers.models import Asset, Capture, Job, utcnow

    values = {"data_dir": str(tmp_path), "retention_days": "30"}
    storage = tmp_path / "storage"
    (storage / "assets" / ("1" * 32)).mkdir(parents=True)
    (storage / "assets" / ("1" * 32) / "mesh.glb").write_bytes(b"glb")
    with _job_store(tmp_path).begin() as session:
        session.add(Capture(id="c" * 32, sha256="c" * 64, size_bytes=1, state="ready",
                            storage_key="captures/none.zip",
                            created_at=utcnow() - timedelta(days=60)))
        session.flush()
        session.add(Job(id="1" * 32, capture_id="c" * 32, state="succeeded",
                        finished_at=utcnow() - timedelta(days=31)))
        session.flush()
        session.add(Asset(id="1" * 32, job_id="1" * 32, files={
            "mesh.glb": {"key": f"assets/{'1' * 32}/mesh.glb"}}))
    with gateway_client(values) as (client, _):  # swept on start
        gateway = client.app.state.gateway

        def gone() -> bool:
            with gateway.sessions() as session:
                left = (session.get(Job, "1" * 32), session.get(Capture, "c" * 32))
                return left == (None, None)
        wait_for(gone, 10, "the retention sweep")
    assert not (storage / "assets" / ("1" * 32) / "mesh.glb").exists()


def test_a_capture_left_validating_by_a_stopped_gateway_is_dropped(tmp_path: Path) -> None:
    from datetime import timedelta

    from workers.models import Capture, utcnow

    zip_path = tmp_path / "storage" / "captures" / "left.zip"
    zip_path.parent.mkdir(parents=True)
    zip_path.write_bytes(b"zip")
    with _job_store(tmp_path).begin() as session:
        for capture_id, age_s in (("a" * 32, 300), ("b" * 32, 5)):
            session.add(Capture(id=capture_id, sha256=capture_id * 2, size_bytes=3,
                                storage_key="captures/left.zip" if age_s > 60 else "x",
                                created_at=utcnow() - timedelta(seconds=age_s)))
    with gateway_client({"data_dir": str(tmp_path), "validation_timeout_s": "60"}) as (
            client, _):
        gateway = client.app.state.gateway

        def swept() -> bool:
            with gateway.sessions() as session:
                return session.get(Capture, "a" * 32) is None
        wait_for(swept, 10, "the sweep of abandoned validations")
        with gateway.sessions() as session:  # one still within its upload's wait is kept
            assert session.get(Capture, "b" * 32) is not None
    assert not zip_path.exists()


def _job_store(data_dir: Path) -> Any:
    """Sessions of the job store in ``data_dir``, as a gateway that ran there left it."""
    from workers.db import init_db, make_engine, make_sessionmaker
    from workers.settings import Settings

    engine = make_engine(Settings(data_dir=data_dir))
    init_db(engine)
    return make_sessionmaker(engine)
