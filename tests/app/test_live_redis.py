"""Live previews across gateways: with a Redis broker, a preview PUT to one gateway reaches the
viewers of another (each with its own hub), through a real redis-server."""

from __future__ import annotations

import contextlib
import json
from collections.abc import Iterator

import httpx
import pytest
from websockets.sync.client import ClientConnection, connect

from app.core.live import PreviewHub
from app.core.live_redis import relay_for
from app.core.security import create_key
from app.main import create_app
from tests.integration.services import Redis, free_port
from tests.live_streams import served, sphere_preview, stream_body
from workers.settings import Settings

pytestmark = pytest.mark.timeout(120)


@pytest.fixture(scope="module")
def two_gateways(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, str, str]]:
    """Two gateways on one Redis broker and one job store; their URLs and a key."""
    folder = tmp_path_factory.mktemp("live-redis")
    redis = Redis(folder / "redis").start()
    settings = Settings(data_dir=folder / "data", broker_url=redis.url)
    first, second = create_app(settings, viewer=False), create_app(settings, viewer=False)
    try:
        with served(first) as first_url, served(second) as second_url:
            with first.state.gateway.sessions() as session:
                _, key = create_key(session, "live-redis")
            yield first_url, second_url, key
    finally:
        redis.stop()


def test_a_preview_reaches_the_viewers_of_every_gateway(two_gateways: tuple[str, str, str]
                                                        ) -> None:
    first_url, second_url, key = two_gateways
    auth = {"Authorization": f"Bearer {key}"}
    stream_id = httpx.post(f"{first_url}/api/v1/streams", json=stream_body(),
                           headers=auth).json()["id"]

    @contextlib.contextmanager
    def viewer(url: str) -> Iterator[ClientConnection]:
        with connect(url.replace("http://", "ws://") + f"/api/v1/streams/{stream_id}/preview",
                     max_size=None) as ws:
            ws.send(json.dumps({"key": key}))
            yield ws

    with viewer(first_url) as here, viewer(second_url) as there:
        for index in range(3):
            preview = sphere_preview(index)
            answer = httpx.put(f"{first_url}/api/v1/streams/{stream_id}/preview",
                               content=preview,
                               headers={**auth, "Content-Type": "application/octet-stream"})
            assert answer.status_code == 204, answer.text
            assert here.recv(timeout=10) == preview
            assert there.recv(timeout=10) == preview


def test_without_redis_the_hub_stays_per_gateway() -> None:
    hub = PreviewHub()
    assert relay_for(None, hub) is None
    assert relay_for("filesystem://", hub) is None
    assert relay_for(f"redis://127.0.0.1:{free_port()}/0", hub) is None  # nobody listens
