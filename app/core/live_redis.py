"""Live previews across gateway processes, through the broker's Redis (pub/sub).

With a Redis broker every gateway publishes the previews it receives on one channel per
stream and hands those of every gateway (its own included) to its own hub, so a viewer sees a
stream whichever gateway its agent sends to. Pub/sub keeps nothing: a gateway that is not
listening at that moment misses a preview, which the next one replaces anyway. Without Redis
(the embedded broker) the hub stays per process.
"""

from __future__ import annotations

import logging
import struct
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import redis

from app.core.live import PreviewHub

log = logging.getLogger(__name__)

CHANNEL_PREFIX = "volumesh:preview:"
MAX_PENDING = 8
"""Previews waiting to be sent to Redis, at most; more are dropped (latest wins anyway)."""
_INDEX = struct.Struct("<q")


def relay_for(broker_url: str | None, hub: PreviewHub) -> RedisRelay | None:
    """A relay through the broker when it is Redis, else None (the hub alone)."""
    if not broker_url or not broker_url.startswith(("redis://", "rediss://")):
        return None
    try:
        return RedisRelay(broker_url, hub)
    except redis.RedisError as exc:
        log.warning("live previews stay within this gateway: Redis is unreachable (%s)", exc)
        return None


class RedisRelay:
    """Publishes this gateway's previews to Redis and feeds every gateway's to ``hub``."""

    def __init__(self, url: str, hub: PreviewHub) -> None:
        self.hub = hub
        self._client = redis.Redis.from_url(url, socket_connect_timeout=5)
        self._pubsub = self._client.pubsub(ignore_subscribe_messages=True)
        self._pubsub.psubscribe(**{CHANNEL_PREFIX + "*": self._received})
        self._listener = self._pubsub.run_in_thread(sleep_time=0.5, daemon=True,
                                                    exception_handler=_listener_failed)
        # One sender thread: publishing up to 3 MB never holds up a request or the loop,
        # and previews leave in the order they came.
        self._sender = ThreadPoolExecutor(1, thread_name_prefix="preview-relay")
        self._lock = threading.Lock()
        self._pending = 0

    def publish(self, stream_id: str, frame_index: int, data: bytes) -> None:
        """Sends the preview to every gateway's hub (in the background)."""
        with self._lock:
            if self._pending >= MAX_PENDING:
                log.warning("stream %s: preview %d dropped, Redis is behind", stream_id,
                            frame_index)
                return
            self._pending += 1
        self._sender.submit(self._send, stream_id, frame_index, data)

    def _send(self, stream_id: str, frame_index: int, data: bytes) -> None:
        try:
            self._client.publish(CHANNEL_PREFIX + stream_id, _INDEX.pack(frame_index) + data)
        except redis.RedisError as exc:
            # Redis is away: this gateway's viewers at least still see the stream.
            log.warning("stream %s: preview not relayed through Redis (%s)", stream_id, exc)
            self.hub.publish(stream_id, frame_index, data)
        finally:
            with self._lock:
                self._pending -= 1

    def _received(self, message: dict[str, Any]) -> None:
        channel, payload = message["channel"], message["data"]
        if not isinstance(payload, bytes) or len(payload) < _INDEX.size:
            return
        stream_id = channel.decode() if isinstance(channel, bytes) else str(channel)
        (frame_index,) = _INDEX.unpack_from(payload)
        self.hub.publish(stream_id[len(CHANNEL_PREFIX):], frame_index,
                         payload[_INDEX.size:])

    def close(self) -> None:
        self._sender.shutdown(wait=True, cancel_futures=True)
        self._listener.stop()
        self._listener.join(5)
        self._pubsub.close()
        self._client.close()


def _listener_failed(exc: BaseException, pubsub: Any, thread: Any) -> None:
    # Redis restarted or the network dropped: redis-py subscribes again on its next read.
    log.warning("live preview relay: Redis listener error (%s); retrying", exc)
    time.sleep(1.0)
