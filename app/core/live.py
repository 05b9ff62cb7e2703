"""Live previews: the hub that relays each stream's newest ``preview.bin`` to its viewers.

The hub is per gateway process: a viewer connected to one gateway sees the previews that
agents send to that gateway (behind a load balancer, route a stream's agent and its viewers to
the same gateway), unless the broker is Redis: then `app.core.live_redis` carries every
gateway's previews to every hub. State changes are also read from the job store by each
viewer's connection (``app.api.routes.live``), so those reach every gateway.

Latest wins: a subscriber holds one preview slot that each newer preview overwrites, so a
slow viewer skips previews and never queues them (memory stays at one preview per viewer).
``publish`` may be called from any thread; subscribers live on the event loop.
"""

from __future__ import annotations

import asyncio
import json
import math
import struct
import threading
import time
from collections import deque
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from dataclasses import dataclass
from typing import Any, TypeGuard

PREVIEW_FORMAT = "volumesh.preview/1"
MAX_HEADER_BYTES = 4096
MAX_POINTS = 200_000
POINT_BYTES = 15
MAX_PREVIEW_BYTES = 4 + MAX_HEADER_BYTES + POINT_BYTES * MAX_POINTS
"""The largest well-formed preview.bin (3 MB)."""
"""3 float32 position components and 3 uint8 colour channels a point."""
FORGET_AFTER_S = 300.0
"""A stream's newest preview is dropped from memory after this long without a newer one."""
_PRUNE_EVERY_S = 30.0
_LENGTH = struct.Struct("<I")

FINAL_STATES = frozenset({"closed", "failed"})


def check_preview(data: bytes) -> int:
    """The header's frame index of a well-formed ``preview.bin``; ValueError saying what is
    wrong otherwise. Checks the header and the length, not the points (the gateway only
    relays them; agent.preview decodes them)."""
    if len(data) < _LENGTH.size:
        raise ValueError(f"{len(data)} bytes: too short for the header length")
    (length,) = _LENGTH.unpack_from(data, 0)
    if length > MAX_HEADER_BYTES:
        raise ValueError(f"header length {length}, at most {MAX_HEADER_BYTES}")
    try:
        header = json.loads(data[_LENGTH.size:_LENGTH.size + length].decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"the header is not UTF-8 JSON ({exc})") from None
    if not isinstance(header, dict) or header.get("format") != PREVIEW_FORMAT:
        raise ValueError(f"the header is not a {PREVIEW_FORMAT} JSON object")
    frame_index, points = header.get("frame_index"), header.get("points")
    if not _is_count(frame_index) or not _is_count(points) or points > MAX_POINTS:
        raise ValueError(f"header frame_index and points must be integers >= 0 (points <= "
                         f"{MAX_POINTS}); got {frame_index!r} and {points!r}")
    captured_at = header.get("captured_at")
    if (not isinstance(captured_at, int | float) or isinstance(captured_at, bool)
            or not math.isfinite(captured_at)):
        raise ValueError(f"header captured_at must be a number, got {captured_at!r}")
    expected = _LENGTH.size + length + POINT_BYTES * points
    if len(data) != expected:
        raise ValueError(f"{len(data)} bytes; its header says {points} points, which take "
                         f"exactly {expected}")
    return frame_index


def _is_count(value: object) -> TypeGuard[int]:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


@dataclass(frozen=True)
class StateChange:
    """A stream stopped receiving: ``state`` assembling, closed or failed."""

    state: str
    capture_id: str | None = None
    error: str | None = None

    def message(self) -> str:
        """The text message a viewer gets: {"state", and capture_id or error when set}."""
        fields = {"state": self.state, "capture_id": self.capture_id, "error": self.error}
        return json.dumps({k: v for k, v in fields.items() if v is not None})


LiveMessage = bytes | StateChange


class Subscription:
    """One viewer's view of a stream: the newest unsent preview and the state changes."""

    def __init__(self) -> None:
        self._preview: bytes | None = None
        self._offered: bytes | None = None
        self._states: deque[StateChange] = deque()
        self._ready = asyncio.Event()

    def offer_preview(self, data: bytes) -> None:
        if data is self._offered:
            return  # a subscriber joining as it is published gets it twice: send it once
        self._preview = self._offered = data  # latest wins: an unsent older one is dropped
        self._ready.set()

    def offer_state(self, change: StateChange) -> None:
        self._states.append(change)
        self._ready.set()

    async def next(self, timeout_s: float | None = None) -> LiveMessage | None:
        """The next message (previews before a state change that followed them), or None
        after ``timeout_s`` without one."""
        if self._preview is None and not self._states:
            self._ready.clear()
            try:
                await asyncio.wait_for(self._ready.wait(), timeout_s)
            except TimeoutError:
                return None
        if self._preview is not None:
            data, self._preview = self._preview, None
            return data
        return self._states.popleft() if self._states else None


@dataclass
class _Latest:
    frame_index: int
    data: bytes | None
    published_at: float
    stopped: bool = False


class PreviewHub:
    """Each stream's newest preview, handed to the stream's subscribers."""

    def __init__(self) -> None:
        self._lock = threading.Lock()  # guards _latest: publish runs on any thread
        self._latest: dict[str, _Latest] = {}
        self._pruned_at = time.monotonic()
        self._subscribers: dict[str, set[Subscription]] = {}  # touched on the loop only
        self._loop: asyncio.AbstractEventLoop | None = None

    def publish(self, stream_id: str, frame_index: int, data: bytes) -> bool:
        """Hands ``data`` to the stream's subscribers unless a preview of the same or a newer
        frame was published already, or the stream stopped; whether it was taken."""
        now = time.monotonic()
        with self._lock:
            latest = self._latest.get(stream_id)
            if latest is not None and (latest.stopped or frame_index <= latest.frame_index):
                return False
            self._latest[stream_id] = _Latest(frame_index, data, now)
            self._prune(now)
            # Scheduled under the lock, so deliveries keep the order of the frame indices.
            self._on_loop(self._deliver_preview, stream_id, data)
        return True

    def change_state(self, stream_id: str, change: StateChange) -> None:
        """Tells the stream's subscribers that it stopped receiving (later previews are
        refused)."""
        with self._lock:
            latest = self._latest.setdefault(stream_id, _Latest(-1, None, time.monotonic()))
            latest.data, latest.stopped = None, True
            self._on_loop(self._deliver_state, stream_id, change)

    @asynccontextmanager
    async def subscribe(self, stream_id: str) -> AsyncIterator[Subscription]:
        """A subscription to the stream, holding its newest preview at once if there is one
        (on the event loop)."""
        self._loop = asyncio.get_running_loop()
        subscription = Subscription()
        self._subscribers.setdefault(stream_id, set()).add(subscription)
        with self._lock:
            latest = self._latest.get(stream_id)
            data = latest.data if latest is not None else None
        if data is not None:
            subscription.offer_preview(data)
        try:
            yield subscription
        finally:
            remaining = self._subscribers.get(stream_id, set())
            remaining.discard(subscription)
            if not remaining:
                self._subscribers.pop(stream_id, None)

    def subscriber_count(self, stream_id: str) -> int:
        return len(self._subscribers.get(stream_id, ()))

    def _deliver_preview(self, stream_id: str, data: bytes) -> None:
        for subscription in self._subscribers.get(stream_id, ()):
            subscription.offer_preview(data)

    def _deliver_state(self, stream_id: str, change: StateChange) -> None:
        for subscription in self._subscribers.get(stream_id, ()):
            subscription.offer_state(change)

    def _on_loop(self, deliver: Callable[[str, Any], None], stream_id: str, item: Any) -> None:
        loop = self._loop
        if loop is None or loop.is_closed():
            return  # nobody ever subscribed on a running loop: nobody to tell
        try:
            on_loop = asyncio.get_running_loop() is loop
        except RuntimeError:
            on_loop = False
        if on_loop:
            deliver(stream_id, item)
        else:
            loop.call_soon_threadsafe(deliver, stream_id, item)

    def _prune(self, now: float) -> None:
        # Bounds memory to the streams that sent a preview lately (called under the lock).
        if now - self._pruned_at < _PRUNE_EVERY_S:
            return
        self._pruned_at = now
        for stream_id in [s for s, latest in self._latest.items()
                          if now - latest.published_at > FORGET_AFTER_S]:
            del self._latest[stream_id]
