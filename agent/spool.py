"""The on-disk spool: every captured frame-set lands here before it is sent.

Layout of the spool folder::

    state.json                    the stream being sent (SpoolState)
    frames/<index:06d>-<timestamp_us>.zip    one frame-set each, oldest index first
    rejected/                     frame-sets the gateway refused (kept for a look)

Files are written to a temporary name and renamed into place (os.replace), so a kill leaves
either the whole file or none. The state is written after its frame-set: a frame-set found
at or after the state's next index was spooled by a run killed before it recorded it, and is
removed on resume (the same source position is captured again under the same index). No
fsync: the spool survives a killed agent; surviving a power cut is not worth a disk flush
per frame-set at 30 per second.
"""

from __future__ import annotations

import json
import os
import re
import threading
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

STATE_FILE = "state.json"
_FRAME_NAME = re.compile(r"(\d{6})-(\d+)\.zip")
_PROGRESS_FIELDS = ("next_index", "next_position", "source_done")


@dataclass(frozen=True)
class SpoolState:
    gateway_url: str
    stream_id: str
    source: str
    depth_scale: float
    cameras: tuple[dict[str, Any], ...]
    """The stream's cameras as the gateway answered them (capture.json's form, with poses
    from the rig when the stream has one)."""
    next_index: int = 0
    """The frame index the next captured frame-set gets."""
    next_position: int = 0
    """The source position to capture next (a replay resumes there)."""
    source_done: bool = False
    """The source has no more frame-sets: what is left is to send the spool and close."""

    def advanced(self, position: int) -> SpoolState:
        """The state after spooling the frame-set at ``position`` under next_index."""
        return replace(self, next_index=self.next_index + 1, next_position=position + 1)


_FIXED_FIELDS = tuple(f.name for f in fields(SpoolState) if f.name not in _PROGRESS_FIELDS)
"""What stays the same while a stream is captured (compared at every write: a change is
written, never a stale copy)."""


@dataclass(frozen=True)
class SpooledFrameSet:
    index: int
    timestamp_us: int
    path: Path
    size_bytes: int


def write_atomic(path: Path, data: bytes) -> None:
    """``data`` at ``path``, whole or not at all (a temporary file, then a rename)."""
    temporary = path.with_name(f".{path.name}.tmp")
    temporary.write_bytes(data)
    os.replace(temporary, path)


class Spool:
    """Frame-sets waiting to be sent, in index order; thread-safe. ``max_bytes`` bounds the
    frame-sets held (one is always let in, so a frame-set larger than the cap still goes)."""

    def __init__(self, root: Path, max_bytes: int) -> None:
        self.root, self.max_bytes = root, max_bytes
        self.frames_dir, self.rejected_dir = root / "frames", root / "rejected"
        try:
            self.frames_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ValueError(f"--spool: cannot use {root} ({exc.strerror})") from None
        self._changed = threading.Condition()
        self._pending: dict[int, SpooledFrameSet] = {}
        self._in_flight: set[int] = set()
        self._bytes = 0
        self._closed = False
        self._fixed: tuple[tuple[Any, ...], str] | None = None
        """The state's unchanging fields and their JSON, last written."""
        for leftover in self.frames_dir.glob(".*.tmp"):  # a write a kill interrupted
            leftover.unlink()
        for path in self.frames_dir.iterdir():
            self._add(path)

    def _add(self, path: Path) -> None:
        match = _FRAME_NAME.fullmatch(path.name)
        if match is None:
            return
        entry = SpooledFrameSet(int(match[1]), int(match[2]), path, path.stat().st_size)
        self._pending[entry.index] = entry
        self._bytes += entry.size_bytes

    # --- state ---------------------------------------------------------------------------

    def read_state(self) -> SpoolState | None:
        path = self.root / STATE_FILE
        if not path.is_file():
            return None
        try:
            document = json.loads(path.read_text())
            return SpoolState(**{**document, "cameras": tuple(document["cameras"])})
        except (OSError, ValueError, TypeError, KeyError) as exc:
            raise ValueError(f"--spool: {path} does not read as a spool state ({exc}); "
                             "delete the folder to start afresh") from None

    def write_state(self, state: SpoolState) -> None:
        write_atomic(self.root / STATE_FILE, self._state_json(state).encode())

    def _state_json(self, state: SpoolState) -> str:
        # Written once per frame-set: the stream's fields and cameras (kilobytes that never
        # change) are encoded once, only the progress each time (dataclasses.asdict and
        # json over eight cameras took 2.7 ms a frame-set, a tenth of the agent's CPU).
        fixed = tuple(getattr(state, name) for name in _FIXED_FIELDS)
        if self._fixed is None or self._fixed[0] != fixed:  # the same cameras: by identity
            document = dict(zip(_FIXED_FIELDS, fixed, strict=True))
            self._fixed = fixed, json.dumps({**document, "cameras": list(state.cameras)})
        progress = json.dumps({name: getattr(state, name) for name in _PROGRESS_FIELDS})
        return f"{self._fixed[1][:-1]}, {progress[1:]}"  # one JSON object of both

    def clear_state(self) -> None:
        (self.root / STATE_FILE).unlink(missing_ok=True)

    # --- frame-sets ----------------------------------------------------------------------

    def drop_from(self, index: int) -> int:
        """Removes frame-sets at ``index`` and after (spooled but never recorded in the
        state); returns how many."""
        with self._changed:
            dropped = [e for i, e in self._pending.items() if i >= index]
            for entry in dropped:
                self._remove(entry)
                entry.path.unlink(missing_ok=True)
            return len(dropped)

    def full(self) -> bool:
        with self._changed:
            return bool(self._pending) and self._bytes >= self.max_bytes

    def put(self, index: int, timestamp_us: int, data: bytes, *,
            wait: bool, stop: threading.Event) -> bool:
        """Spools a frame-set. When the spool is full: waits for room (``wait``, until
        ``stop``), or returns False at once (the frame-set is not spooled)."""
        with self._changed:
            while self._pending and self._bytes + len(data) > self.max_bytes:
                if not wait or stop.is_set():
                    return False
                self._changed.wait(0.2)
        path = self.frames_dir / f"{index:06d}-{timestamp_us}.zip"
        write_atomic(path, data)
        with self._changed:
            self._pending[index] = SpooledFrameSet(index, timestamp_us, path, len(data))
            self._bytes += len(data)
            self._changed.notify_all()
        return True

    def take(self, timeout_s: float) -> SpooledFrameSet | None:
        """The oldest frame-set no sender holds, now held; None after ``timeout_s``."""
        with self._changed:
            if not self._changed.wait_for(lambda: self._closed or self._free(), timeout_s):
                return None
            free = self._free()
            if not free:
                return None
            entry = self._pending[min(free)]
            self._in_flight.add(entry.index)
            return entry

    def _free(self) -> list[int]:
        return [i for i in self._pending if i not in self._in_flight]

    def acknowledge(self, entry: SpooledFrameSet) -> None:
        """The gateway has it: gone from the spool."""
        entry.path.unlink(missing_ok=True)
        with self._changed:
            self._remove(entry)

    def reject(self, entry: SpooledFrameSet) -> Path:
        """The gateway refused it: moved to rejected/ (out of the way, kept for a look)."""
        self.rejected_dir.mkdir(exist_ok=True)
        target = self.rejected_dir / entry.path.name
        os.replace(entry.path, target)
        with self._changed:
            self._remove(entry)
        return target

    def _remove(self, entry: SpooledFrameSet) -> None:
        if self._pending.pop(entry.index, None) is not None:
            self._bytes -= entry.size_bytes
        self._in_flight.discard(entry.index)
        self._changed.notify_all()

    def wait_empty(self, timeout_s: float) -> bool:
        with self._changed:
            return self._changed.wait_for(lambda: not self._pending, timeout_s)

    def size(self) -> tuple[int, int]:
        """(frame-sets, bytes) spooled, sent or not yet."""
        with self._changed:
            return len(self._pending), self._bytes

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        """Wakes every sender waiting in take (it then gets None)."""
        with self._changed:
            self._closed = True
            self._changed.notify_all()
