"""Uploads' housekeeping against real gateways: the byte counter, the stalled-body timeout and
the sweep of stale partial uploads while the gateway runs."""

from __future__ import annotations

import json
import os
import re
import socket
import time
from pathlib import Path

from tests.app.conftest import Service
from tests.integration.services import (
    Gateway,
    base_env,
    create_key,
    gateway_client,
    wait_for,
)

ZIP = {"Content-Type": "application/zip"}


def _uploaded_bytes(service: Service) -> float:
    text = service.client.get("/metrics").text
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
