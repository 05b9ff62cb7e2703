"""Live previews to the gateway as soon as they are made, beside the frame-sets.

A preview is about now: it never waits behind frame-sets in the spool and is never spooled
itself. One waits at most; a newer one replaces it. A preview the gateway does not take
(away, slow, refusing) is counted and forgotten.
"""

from __future__ import annotations

import threading

import httpx

from agent.gateway import Gateway
from agent.stats import Stats

TIMEOUT_S = 2.0
"""A preview older than this is not worth delivering."""


class PreviewSender:
    """A thread sending the newest preview offered; ``offer`` never blocks."""

    def __init__(self, gateway: Gateway, stream_id: str, stats: Stats) -> None:
        self.stream_id, self.stats = stream_id, stats
        # A connection of its own: never queued behind the frame-sets' uploads.
        self.client = httpx.Client(base_url=gateway.client.base_url, timeout=TIMEOUT_S,
                                   headers={"Authorization":
                                            gateway.client.headers["Authorization"]})
        self._waiting: bytes | None = None
        self._changed = threading.Condition()
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="preview", daemon=True)

    def start(self) -> PreviewSender:
        self._thread.start()
        return self

    def offer(self, data: bytes) -> None:
        with self._changed:
            if self._waiting is not None:
                self.stats.add(previews_skipped=1)
            self._waiting = data
            self._changed.notify()

    def close(self) -> None:
        with self._changed:
            self._closed = True
            self._changed.notify()
        self._thread.join(TIMEOUT_S + 1.0)
        self.client.close()

    def _next(self) -> bytes | None:
        with self._changed:
            while self._waiting is None and not self._closed:
                self._changed.wait()
            data, self._waiting = self._waiting, None
            return None if self._closed else data

    def _run(self) -> None:
        while (data := self._next()) is not None:
            try:
                response = self.client.put(f"/streams/{self.stream_id}/preview", content=data,
                                           headers={"Content-Type": "application/octet-stream"})
                sent = response.status_code == 204
            except httpx.TransportError:
                sent = False
            self.stats.add(**({"previews_sent": 1} if sent else {"previews_skipped": 1}))
