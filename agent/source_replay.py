"""Replayed sources: Azure Kinect recordings and stored captures, frame-set by frame-set."""

from __future__ import annotations

from collections.abc import Generator, Iterator, Sequence
from contextlib import closing
from pathlib import Path
from typing import cast

import numpy as np

from agent.sources import DEFAULT_FPS, FrameSet, SourceInfo
from pipeline.io.capture_io import open_capture
from pipeline.io.k4a_import import (
    DEPTH_SCALE_M,
    open_recordings,
    recorded_view,
)
from pipeline.io.k4a_import import iter_frame_sets as iter_recorded_frame_sets
from pipeline.io.k4a_mkv import CameraFrame
from pipeline.io.k4a_sync import FrameSet as MatchedFrames

RecordedSet = MatchedFrames[CameraFrame]

MAX_STREAM_FPS = 120.0


class MkvSource:
    """k4arecorder recordings of one rig, one per device, matched into frame-sets as
    ``volumesh import-mkv`` matches them. A position counts every matched frame-set, complete
    or not; incomplete ones (a device lost a frame, or had not started) are skipped."""

    def __init__(self, paths: Sequence[Path]) -> None:
        self.recordings = open_recordings(paths)
        self.info = SourceInfo(cameras=self.recordings.cameras, depth_scale=DEPTH_SCALE_M,
                               fps=float(round(1e6 / self.recordings.frame_period_us)),
                               live=False)  # the device records at 5, 15 or 30 fps
        self.incomplete = 0

    def frame_sets(self, first_position: int) -> Iterator[FrameSet]:
        cameras = self.recordings.cameras
        # A generator: closing it closes the recordings of a replay stopped part-way.
        matched = cast(Generator[RecordedSet, None, None],
                       iter_recorded_frame_sets(self.recordings))
        with closing(matched):
            for position, frame_set in enumerate(matched):
                if position < first_position:  # spooled by an earlier run
                    continue
                if not frame_set.complete:
                    self.incomplete += 1
                    continue
                views = tuple(recorded_view(camera, position, frame)  # type: ignore[arg-type]
                              for camera, frame in zip(cameras, frame_set.frames, strict=True))
                yield FrameSet(position, max(frame_set.timestamp_us, 0), views)

    def close(self) -> None:
        """Nothing held open: the recordings are open only while frame_sets runs."""


class CaptureSource:
    """A capture (directory or zip) with many frames; a position is a frame of capture.json.
    Its image files go on as stored: no decode and re-encode (depth PNGs cost ~5 ms each to
    decode, more than eight cameras at 30 fps leave a small PC)."""

    def __init__(self, path: Path, fps: float | None) -> None:
        self.reader = open_capture(path)
        meta = self.reader.meta
        self.timestamps_us, rate = _timing([f.timestamp_us for f in meta.frames], fps)
        self.info = SourceInfo(cameras=meta.cameras, depth_scale=meta.depth_scale, fps=rate,
                               live=False)

    def frame_sets(self, first_position: int) -> Iterator[FrameSet]:
        meta = self.reader.meta
        for position in range(first_position, len(meta.frames)):
            index = meta.frames[position].index
            views = tuple(self.reader.read_image_files(c.id, index) for c in meta.cameras)
            yield FrameSet(position, self.timestamps_us[position], views)

    def close(self) -> None:
        self.reader.close()


def _timing(stored_us: list[int], fps: float | None) -> tuple[list[int], float]:
    """The frames' timestamps and frame rate: the capture's own where its timestamps increase
    (the rate from their median interval), else evenly spaced at ``fps`` (a capture written
    without timestamps has 0 everywhere)."""
    if len(stored_us) > 1 and all(b > a for a, b in zip(stored_us, stored_us[1:], strict=False)):
        interval_us = float(np.median(np.diff(stored_us)))
        return stored_us, min(1e6 / interval_us, MAX_STREAM_FPS)
    rate = fps or DEFAULT_FPS
    return [round(i * 1e6 / rate) for i in range(len(stored_us))], rate
