"""The capture loop: frame-sets from the source, encoded, into the spool, the state after each.

A replay is paced by its timestamps (unless fast) and waits when the spool is full; a live
source is never held up: when the spool is full its frame-sets are dropped and counted.
Every 1/preview_hz seconds of device time a frame-set also makes a live preview, when every
camera's pose is known; it goes to ``on_preview`` (the preview sender), not into the spool.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Executor, ThreadPoolExecutor
from dataclasses import dataclass, replace

from agent import preview as preview_format
from agent.framesets import encode_frame_set, preview_inputs
from agent.sources import FrameSet, Source
from agent.spool import Spool, SpoolState
from agent.stats import Stats
from pipeline.capture import CameraInfo

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CaptureSettings:
    fast: bool = False
    """Replay as fast as the spool takes it, not at the source's frame rate."""
    preview_hz: float = 10.0
    """Previews per second of device time; 0: none."""
    posed_cameras: tuple[CameraInfo, ...] | None = None
    """The source's cameras with their poses (in its order); None: no preview."""
    encoder_threads: int = min(4, os.cpu_count() or 1)


class Pacer:
    """Holds each frame-set until its timestamp, counted from the first one's arrival."""

    def __init__(self, enabled: bool) -> None:
        self.enabled = enabled
        self.origin: tuple[float, int] | None = None

    def wait(self, timestamp_us: int, stop: threading.Event) -> None:
        if not self.enabled:
            return
        now_s = time.monotonic()
        if self.origin is None:
            self.origin = (now_s, timestamp_us)
            return
        due_s = self.origin[0] + (timestamp_us - self.origin[1]) / 1e6
        if due_s > now_s:
            stop.wait(due_s - now_s)


class Previews:
    """Whether a frame-set is due a preview, and its preview.bin."""

    def __init__(self, settings: CaptureSettings, depth_scale: float) -> None:
        self.cameras = settings.posed_cameras
        self.interval_us = 1e6 / settings.preview_hz if settings.preview_hz > 0 else None
        self.depth_scale = depth_scale
        self.last_slot: int | None = None

    def due(self, timestamp_us: int) -> bool:
        # Slots of one interval each: a preview in every slot, however the frame rate divides.
        if self.cameras is None or self.interval_us is None:
            return False
        slot = int(timestamp_us // self.interval_us)
        if self.last_slot is not None and slot <= self.last_slot:
            return False
        self.last_slot = slot
        return True

    def encode(self, frame_set: FrameSet, index: int, captured_at: float) -> bytes | None:
        assert self.cameras is not None
        try:
            depth_m, colors, cameras = preview_inputs(frame_set.views, self.cameras,
                                                      self.depth_scale)
            return preview_format.encode_preview(depth_m, colors, cameras, index, captured_at)
        except ValueError as exc:  # a preview never stops the capture
            log.warning("no previews: %s", exc)
            self.cameras = None
            return None


def run_capture(source: Source, spool: Spool, state: SpoolState, settings: CaptureSettings,
                stats: Stats, stop: threading.Event,
                on_preview: Callable[[bytes], None] = lambda _: None) -> SpoolState:
    """Captures from the state's next position until the source ends (the state returned
    says source_done) or ``stop``; each preview made goes to ``on_preview``."""
    pacer = Pacer(enabled=not (settings.fast or source.info.live))
    keeper = _Keeper(spool, stats, Previews(settings, source.info.depth_scale),
                     source.info.live, stop, on_preview)
    with ThreadPoolExecutor(settings.encoder_threads, thread_name_prefix="encode") as pool:
        for frame_set in source.frame_sets(state.next_position):
            pacer.wait(frame_set.timestamp_us, stop)
            if stop.is_set():
                return state
            state = keeper.keep(frame_set, state, pool)
    if stop.is_set():
        return state
    state = replace(state, source_done=True)
    spool.write_state(state)
    return state


@dataclass
class _Keeper:
    """Encodes a frame-set under the next index and spools it, or drops it (live, full)."""

    spool: Spool
    stats: Stats
    previews: Previews
    live: bool
    stop: threading.Event
    on_preview: Callable[[bytes], None]

    def keep(self, frame_set: FrameSet, state: SpoolState, pool: Executor) -> SpoolState:
        """The state after the frame-set: advanced when it was spooled."""
        if self.live and self.spool.full():  # no encoding for what cannot be kept
            self.stats.add(dropped=1)
            return state
        index, captured_at = state.next_index, time.time()
        if self.previews.due(frame_set.timestamp_us):
            preview = self.previews.encode(frame_set, index, captured_at)
            if preview is not None:
                self.on_preview(preview)
        data = encode_frame_set(frame_set.views, index, pool)
        if not self.spool.put(index, frame_set.timestamp_us, data, wait=not self.live,
                              stop=self.stop):
            if not self.stop.is_set():
                self.stats.add(dropped=1)
            return state
        state = state.advanced(frame_set.position)
        self.spool.write_state(state)
        self.stats.add(captured=1, captured_bytes=len(data))
        return state


def posed(cameras: Sequence[CameraInfo], stream_cameras: Sequence[CameraInfo]
          ) -> tuple[CameraInfo, ...] | None:
    """The source's cameras with the stream's poses (the rig's, with --rig); None unless
    every camera has one."""
    by_id = {c.id: c for c in stream_cameras}
    poses = [by_id[c.id].world_from_depth if c.id in by_id else None for c in cameras]
    if any(p is None for p in poses):
        return None
    return tuple(replace(c, world_from_depth=p) for c, p in zip(cameras, poses, strict=True))
