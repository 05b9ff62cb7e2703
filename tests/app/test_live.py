"""The live preview end to end: frame-sets PUT to a real gateway (uvicorn, the test service's
store, broker and worker) reach a real WebSocket client, newest first, with the key checked."""

from __future__ import annotations

import asyncio
import contextlib
import json
import threading
from collections.abc import Iterator
from typing import Any

import httpx
import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import ClientConnection, connect

from agent.preview import decode_preview
from app.api.routes import live as live_route
from app.core.live import PreviewHub, StateChange, check_preview
from app.core.security import create_key
from app.main import create_app
from tests.app.conftest import Service
from tests.live_streams import big_preview, frame_set, served, sphere_preview, stream_body

pytestmark = pytest.mark.timeout(180)


class Gateway:
    def __init__(self, url: str, key: str) -> None:
        self.url, self.key = url, key
        self.http = httpx.Client(base_url=url, headers={"Authorization": f"Bearer {key}"},
                                 timeout=30)

    def create_stream(self) -> str:
        answer = self.http.post("/api/v1/streams", json=stream_body())
        assert answer.status_code == 201, answer.text
        return str(answer.json()["id"])

    def put(self, stream_id: str, index: int) -> dict[str, Any]:
        answer = self.http.put(f"/api/v1/streams/{stream_id}/frames/{index}",
                               content=frame_set(index),
                               headers={"Content-Type": "application/zip"})
        assert answer.status_code in (200, 201), answer.text
        return dict(answer.json())

    def preview(self, stream_id: str, data: bytes) -> httpx.Response:
        return self.http.put(f"/api/v1/streams/{stream_id}/preview", content=data,
                             headers={"Content-Type": "application/octet-stream"})

    @contextlib.contextmanager
    def socket(self, stream_id: str, key: str | None = None, **options: Any
               ) -> Iterator[ClientConnection]:
        """A WebSocket client of the stream's preview that has sent its key."""
        url = self.url.replace("http://", "ws://") + f"/api/v1/streams/{stream_id}/preview"
        with connect(url, max_size=None, open_timeout=10, **options) as ws:
            ws.send(json.dumps({"key": self.key if key is None else key}))
            yield ws


@pytest.fixture(scope="module")
def gateway(service: Service) -> Iterator[Gateway]:
    """A second gateway process-alike on the service's settings, served for real (the
    TestClient cannot carry a WebSocket client library)."""
    with served(create_app(service.settings, viewer=False)) as url:
        gw = Gateway(url, service.key)
        yield gw
        gw.http.close()


def _index(message: str | bytes) -> int:
    assert isinstance(message, bytes), message
    return decode_preview(message).frame_index


def _close_code(ws: ClientConnection, timeout_s: float = 10) -> int:
    with pytest.raises(ConnectionClosed) as closed:
        ws.recv(timeout=timeout_s)
    assert closed.value.rcvd is not None
    return closed.value.rcvd.code


def test_previews_arrive_in_order_and_as_sent(gateway: Gateway) -> None:
    stream_id = gateway.create_stream()
    with gateway.socket(stream_id) as ws:
        for index in range(4):
            preview = sphere_preview(index)
            assert gateway.preview(stream_id, preview).status_code == 204
            assert ws.recv(timeout=10) == preview  # the agent's bytes, unchanged
        # An older frame's preview (late, or sent again) is not relayed.
        assert gateway.preview(stream_id, sphere_preview(2)).status_code == 204
        assert gateway.preview(stream_id, sphere_preview(10)).status_code == 204
        assert _index(ws.recv(timeout=10)) == 10
        assert gateway.preview(stream_id, sphere_preview(7)).status_code == 204
        malformed = gateway.preview(stream_id, b"\x10\x00\x00\x00not a preview")
        assert malformed.status_code == 422, malformed.text
        assert malformed.json()["type"].endswith("/invalid-preview")
        assert gateway.put(stream_id, 12)["stored"] is True  # frame-sets are another path
        assert gateway.preview(stream_id, sphere_preview(13)).status_code == 204
        assert _index(ws.recv(timeout=10)) == 13
    # A late viewer gets the newest preview at once.
    with gateway.socket(stream_id) as ws:
        assert _index(ws.recv(timeout=10)) == 13


def test_a_preview_needs_a_receiving_stream_of_the_caller(gateway: Gateway,
                                                          service: Service) -> None:
    stream_id = gateway.create_stream()
    with service.client.app.state.gateway.sessions() as session:  # type: ignore[attr-defined]
        _, other_key = create_key(session, "other previewer", project="elsewhere")
    other = gateway.http.put(f"/api/v1/streams/{stream_id}/preview", content=sphere_preview(0),
                             headers={"Authorization": f"Bearer {other_key}"})
    assert other.status_code == 404, other.text
    too_big = gateway.preview(stream_id, b"\0" * (4 + 4096 + 15 * 200_000 + 1))
    assert too_big.status_code == 413, too_big.text
    assert gateway.put(stream_id, 0)["stored"] is True
    assert gateway.http.post(f"/api/v1/streams/{stream_id}/close").status_code == 202
    late = gateway.preview(stream_id, sphere_preview(1))
    assert late.status_code == 409 and late.json()["type"].endswith("/stream-not-receiving")


def test_a_slow_viewer_skips_to_the_newest(gateway: Gateway) -> None:
    stream_id = gateway.create_stream()
    # The client queues one message and stops reading the socket: the buffers fill and the
    # server must drop previews rather than queue them.
    with gateway.socket(stream_id, max_queue=1) as ws:
        sent = 40
        for index in range(sent):  # 3 MB each: the socket buffers hold a few at most
            assert gateway.preview(stream_id, big_preview(index, points=200_000)).status_code == 204
        received = []
        while not received or received[-1] != sent - 1:
            received.append(_index(ws.recv(timeout=20)))
    assert received == sorted(received)
    assert len(received) < sent / 2, received


def test_a_bad_or_missing_key_closes_with_4401(gateway: Gateway, service: Service,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    stream_id = gateway.create_stream()
    with gateway.socket(stream_id, key="vmk_" + "x" * 43) as ws:
        assert _close_code(ws) == 4401
    url = gateway.url.replace("http://", "ws://") + f"/api/v1/streams/{stream_id}/preview"
    with connect(url) as ws:
        ws.send("not json")
        assert _close_code(ws) == 4401
    monkeypatch.setattr(live_route, "FIRST_MESSAGE_S", 0.3)
    with connect(url) as ws:  # says nothing
        assert _close_code(ws) == 4401


def test_another_owners_stream_closes_with_4404(gateway: Gateway, service: Service) -> None:
    stream_id = gateway.create_stream()
    with service.client.app.state.gateway.sessions() as session:  # type: ignore[attr-defined]
        _, other_key = create_key(session, "other", project="elsewhere")
    with gateway.socket(stream_id, key=other_key) as ws:
        assert _close_code(ws) == 4404
    with gateway.socket("0" * 32) as ws:
        assert _close_code(ws) == 4404
    with gateway.socket("not-an-id") as ws:
        assert _close_code(ws) == 4404


def test_closing_the_stream_tells_the_viewer(gateway: Gateway) -> None:
    stream_id = gateway.create_stream()
    with gateway.socket(stream_id) as ws:
        assert gateway.put(stream_id, 0)["stored"] is True
        assert gateway.preview(stream_id, sphere_preview(0)).status_code == 204
        assert _index(ws.recv(timeout=10)) == 0
        answer = gateway.http.post(f"/api/v1/streams/{stream_id}/close")
        assert answer.status_code == 202, answer.text
        states = [json.loads(ws.recv(timeout=10))]
        if states[0]["state"] == "assembling":  # the worker may be quicker than the relay
            states.append(json.loads(ws.recv(timeout=60)))
        assert states[-1]["state"] == "closed", states
        stream = gateway.http.get(f"/api/v1/streams/{stream_id}").json()
        assert states[-1]["capture_id"] == stream["capture_id"] is not None
        assert _close_code(ws) == 1000
    # A viewer of a closed stream hears so at once.
    with gateway.socket(stream_id) as ws:
        assert json.loads(ws.recv(timeout=10))["state"] == "closed"
        assert _close_code(ws) == 1000


def test_the_gateway_check_agrees_with_the_agent() -> None:
    preview = sphere_preview(5)
    assert check_preview(preview) == 5
    assert check_preview(big_preview(1, points=0)) == 1
    for bad in (b"", preview[:-1], preview + b"\0", b"\xff\xff\x00\x00" + preview[4:],
                preview.replace(b"volumesh.preview/1", b"volumesh.preview/9")):
        with pytest.raises(ValueError):
            check_preview(bad)


def test_the_hub_keeps_the_newest_from_any_thread() -> None:
    async def scenario() -> list[int | str]:
        hub = PreviewHub()
        async with hub.subscribe("s") as subscription:
            publishers = [threading.Thread(target=hub.publish, args=("s", i, bytes([i])))
                          for i in range(50)]
            for thread in publishers:
                thread.start()
            for thread in publishers:
                thread.join()
            assert hub.publish("s", 3, b"old") is False
            seen: list[int | str] = []
            while (message := await subscription.next(0.2)) is not None:
                seen.append(message[0] if isinstance(message, bytes) else message.state)
            hub.change_state("s", StateChange("assembling"))
            assert hub.publish("s", 99, b"late") is False  # a stopped stream takes none
            message = await subscription.next(1)
            assert isinstance(message, StateChange)
            seen.append(message.state)
        assert hub.subscriber_count("s") == 0
        return seen

    assert asyncio.run(scenario()) == [49, "assembling"]
