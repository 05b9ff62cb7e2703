"""A gateway stopped in the middle of an upload: the client gets an error, and no capture,
stored object or partial file is left once a gateway runs again."""

from __future__ import annotations

import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from tests.integration.services import Gateway, base_env, create_key, wait_for

pytestmark = pytest.mark.slow
CHUNK = 256 * 1024


def _slow_body(sent: list[int], stop: threading.Event) -> Iterator[bytes]:
    block = b"PK\x03\x04" + bytes(CHUNK - 4)
    for _ in range(400):  # 100 MB at most; the gateway dies long before
        if stop.is_set():
            return
        sent[0] += len(block)
        yield block
        time.sleep(0.01)


@pytest.mark.parametrize("how", [signal.SIGKILL, signal.SIGTERM], ids=["sigkill", "sigterm"])
def test_gateway_restart_during_upload(tmp_path: Path, how: signal.Signals) -> None:
    data_dir = tmp_path / "data"
    env = base_env(data_dir=str(data_dir), stale_upload_s="1", embedded_worker="false")
    key = create_key(env)
    gateway = Gateway(env, tmp_path / "gateway-1.log").start()
    sent, stop = [0], threading.Event()
    outcome: dict[str, Any] = {}

    def upload() -> None:
        try:
            with httpx.Client(timeout=30) as client:
                response = client.post(
                    gateway.url + "/api/v1/captures", content=_slow_body(sent, stop),
                    headers={"Authorization": f"Bearer {key}",
                             "Content-Type": "application/zip"})
                outcome["status"] = response.status_code
                outcome["problem"] = response.json()
        except httpx.TransportError as exc:
            outcome["error"] = exc

    thread = threading.Thread(target=upload)
    thread.start()
    try:
        wait_for(lambda: sent[0] > 4 * 1024 * 1024, 30, "part of the upload to be sent")
        parts = list((data_dir / "tmp").glob("upload-*.part"))
        assert len(parts) == 1 and parts[0].stat().st_size > 0  # streamed to disk as it comes
        gateway.kill(how)
        thread.join(30)
    finally:
        stop.set()
        thread.join(5)
    # The client learns the upload failed: a transport error (connection dropped) or an
    # error status, never a capture id.
    if how == signal.SIGKILL:  # nothing can answer: the connection drops
        assert isinstance(outcome.get("error"), httpx.TransportError), outcome
    else:  # a stopping gateway answers with a retryable problem
        assert outcome.get("status") == 503, outcome
        assert outcome.get("problem", {}).get("type", "").endswith("upload-interrupted")
    time.sleep(1.2)  # older than VOLUMESH_STALE_UPLOAD_S, so the next gateway clears it
    again = Gateway(env, tmp_path / "gateway-2.log").start()
    try:
        listed = httpx.get(again.url + "/api/v1/captures",
                           headers={"Authorization": f"Bearer {key}"}).json()
        assert listed["total"] == 0 and listed["items"] == []
        assert not list((data_dir / "tmp").glob("upload-*"))
        assert not list((data_dir / "storage").rglob("*.zip"))
    finally:
        again.stop()
