"""Frame-sets across devices: frames matched by timestamp within a sync window.

Each device yields its frames in timestamp order. The earliest pending frame of all devices
opens a frame-set; every device whose pending frame lies within the window after it joins. A
frame-set with every device is complete; one without is incomplete and says why each missing
device is missing: it has not started yet, it has ended, or it dropped that frame.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Generic, TypeVar

T = TypeVar("T")


@dataclass(frozen=True)
class FrameSet(Generic[T]):
    """Frames of one instant, one slot per device (None where that device has no frame)."""

    timestamp_us: int
    """The earliest of the members' timestamps."""
    frames: tuple[T | None, ...]
    dropped: tuple[int, ...] = ()
    """Devices missing while they were recording: a frame lost, not the ends of recordings."""

    @property
    def complete(self) -> bool:
        return all(frame is not None for frame in self.frames)


def match_frames(streams: Sequence[Iterator[T]], timestamp_us: Callable[[T], int],
                 sync_window_us: int) -> Iterator[FrameSet[T]]:
    """Every frame of ``streams`` once, in frame-sets: complete ones, and incomplete ones where
    a device has no frame within ``sync_window_us`` of the set's earliest. Reads one frame
    ahead per device; the streams run to their ends (so that every frame is accounted for)."""
    if sync_window_us < 0:
        raise ValueError(f"sync window: must be at least 0 us, got {sync_window_us}")
    heads: list[T | None] = [next(stream, None) for stream in streams]
    started = [False] * len(streams)
    while any(head is not None for head in heads):
        times = [timestamp_us(h) if h is not None else None for h in heads]
        first = min(t for t in times if t is not None)
        members = [t is not None and t - first <= sync_window_us for t in times]
        frames = tuple(heads[i] if members[i] else None for i in range(len(heads)))
        dropped = tuple(i for i, joined in enumerate(members)
                        if not joined and started[i] and heads[i] is not None)
        yield FrameSet(first, frames, dropped)
        for i, joined in enumerate(members):
            if joined:
                started[i] = True
                heads[i] = next(streams[i], None)
