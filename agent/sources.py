"""Where frame-sets come from: a source string (``mkv:A.mkv,B.mkv``, ``capture:DIR``,
``synthetic``, ``k4a``) opened as a :class:`Source`.

Every source gives its cameras once (:class:`SourceInfo`) and then frame-sets in order, each
with its *position*: the source's own count of frame-sets, so that a replay stopped part-way
resumes at the next position it did not spool (no frame-set twice, none skipped).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from pipeline.capture import CameraInfo
from pipeline.io.capture_io import StoredFiles, StoredView

SOURCE_KINDS = ("mkv:A.mkv,B.mkv,...", "capture:DIR", "synthetic", "k4a")
DEFAULT_FPS = 30.0
"""The rate of a capture without frame timestamps, and of the synthetic rig."""


@dataclass(frozen=True)
class SourceInfo:
    """What a source says once, before its frame-sets."""

    cameras: tuple[CameraInfo, ...]
    depth_scale: float
    """Metres per depth unit of every frame-set's depth."""
    fps: float
    live: bool
    """Live: frames come at the devices' pace and are dropped when the spool is full. Replay:
    frames wait for room and are paced by their timestamps (unless fast)."""


CameraImages = StoredView | StoredFiles
"""One camera's images: as arrays (depth in the source's units, colour as RGB or the
recorded JPEG), or as a capture's files, passed on as stored."""


@dataclass(frozen=True)
class FrameSet:
    """Every camera's images of one instant, in the cameras' order."""

    position: int
    timestamp_us: int
    """Device timestamp, microseconds (>= 0)."""
    views: tuple[CameraImages, ...]


class Source(Protocol):
    info: SourceInfo

    def frame_sets(self, first_position: int) -> Iterator[FrameSet]:
        """Frame-sets from ``first_position`` on (a live source just counts from there)."""
        ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class SourceOptions:
    fps: float | None = None
    """Frame rate of a capture without timestamps and of the synthetic rig (default 30)."""
    frames: int = 300
    """Frame-sets of the synthetic source."""

    def __post_init__(self) -> None:
        if self.fps is not None and not 0 < self.fps <= 120:
            raise ValueError(f"--fps: must be in (0, 120], got {self.fps:g}")
        if self.frames < 1:
            raise ValueError(f"--frames: must be at least 1, got {self.frames}")


def open_source(spec: str, options: SourceOptions = SourceOptions()) -> Source:
    """The source a source string names; ValueError of one line for an unknown kind, a
    missing file or a recording/capture that does not read."""
    kind, _, argument = spec.partition(":")
    if kind == "mkv" and argument:
        from agent.source_replay import MkvSource

        return MkvSource([Path(p) for p in argument.split(",") if p])
    if kind == "capture" and argument:
        from agent.source_replay import CaptureSource

        return CaptureSource(Path(argument), options.fps)
    if spec == "synthetic":
        from agent.source_synthetic import SyntheticSource

        return SyntheticSource(options.frames, options.fps or DEFAULT_FPS)
    if spec == "k4a":
        from agent.source_k4a import open_k4a

        return open_k4a()
    raise ValueError(f"--source: unknown source {spec!r}; one of {' | '.join(SOURCE_KINDS)}")
