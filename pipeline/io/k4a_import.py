"""Azure Kinect recordings of one rig to a capture (format v1) with many frames.

Each recording is one device. Frames are matched across devices by device timestamp (block
timestamp plus the recording's start offset, less a subordinate's capture delay after the
master's trigger) within a sync window; a frame-set is kept when every device has a depth
image in it. Recordings carry no extrinsics, so the capture has no poses: calibrate a
calibration recording imported the same way, and reconstruct with its rig.
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable, Generator, Iterator, Sequence
from contextlib import closing
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from pipeline.capture import (
    CAMERA_ID_PATTERN,
    FORMAT_ID,
    CameraInfo,
    CaptureMeta,
    FrameInfo,
    Target,
)
from pipeline.io.capture_io import StoredView, write_capture
from pipeline.io.capture_json import meta_from_json
from pipeline.io.capture_threads import write_capture_threaded
from pipeline.io.k4a_calibration import color_from_depth, color_intrinsics, depth_intrinsics
from pipeline.io.k4a_mkv import (
    DEPTH_UNIT_M,
    CameraFrame,
    RecordingInfo,
    iter_camera_frames,
    read_recording_info,
)
from pipeline.io.k4a_sync import FrameSet, match_frames

DEPTH_SCALE_M = DEPTH_UNIT_M
"""The capture's depth_scale: the device's millimetres, so depth is written as recorded (the
StoredViews carry the recorded values, which are in these units by this equality)."""


@dataclass(frozen=True)
class ImportConfig:
    sync_window_us: int | None = None
    """Frames of one frame-set lie within this of its earliest; None: half a frame period."""
    writer_threads: int = 2
    """Views written at once: deflate, CRC and file writes release the GIL, so two threads keep
    two cores busy while the calling thread reads the recordings (with 1, that thread writes
    too, one view after another)."""
    target: Target | None = None
    """The calibration target the colour images show, for a calibration recording."""


@dataclass(frozen=True)
class Recordings:
    """Recordings of one rig, checked to fit together, and their cameras in the capture."""

    infos: tuple[RecordingInfo, ...]
    cameras: tuple[CameraInfo, ...]
    sync_window_us: int
    warnings: tuple[str, ...] = ()
    writer_threads: int = 1
    target: Target | None = None

    @property
    def frame_period_us(self) -> int:
        return self.infos[0].frame_period_us

    def shared_span_us(self) -> tuple[int, int]:
        """(first, last) trigger time, microseconds, that every recording covers."""
        starts = [i.start_offset_us - i.subordinate_delay_us for i in self.infos]
        return max(starts), min(s + i.duration_us for s, i in zip(starts, self.infos, strict=True))


@dataclass(frozen=True)
class ImportReport:
    camera_ids: tuple[str, ...]
    frame_sets: int
    """Complete frame-sets written."""
    dropped: int
    """Incomplete frame-sets while every device was recording (a device lost a frame)."""
    dropped_by_camera: dict[str, int]
    outside: int
    """Incomplete frame-sets before every device had started or after one had stopped."""
    missing_color: int
    """Frames of devices with colour whose colour image was missing."""
    sync_window_us: int
    frame_period_us: int
    warnings: tuple[str, ...] = field(default=())


def read_target(path: str | Path) -> Target:
    """A calibration target from a JSON file holding what capture.json's ``target`` holds
    (docs/capture-format.md), checked by the capture.json reader; ValueError naming the file
    and the field."""
    path = Path(path)
    try:
        target = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: not a readable JSON file ({exc})") from None
    if target is None:
        raise ValueError(f"{path.name}: holds null, not a target")
    stub = {"width": 1, "height": 1, "fx": 1.0, "fy": 1.0, "cx": 0.0, "cy": 0.0}
    document = {"format": FORMAT_ID, "depth_scale": DEPTH_SCALE_M, "frames": [{"index": 0}],
                "cameras": [{"id": "cam0", "depth_intrinsics": stub}], "target": target}
    try:
        parsed = meta_from_json(document).target
    except ValueError as exc:  # 'capture.json: target.boards[0].x: ...' is about this file
        where = str(exc).removeprefix("capture.json: target")
        where = where[1:] if where.startswith(".") else where.removeprefix(": ")
        raise ValueError(f"{path.name}: {where}") from None
    assert parsed is not None
    return parsed


def _camera_ids(infos: Sequence[RecordingInfo]) -> tuple[str, ...]:
    """Serial numbers, so that ids stay the same across recordings of the rig (a calibration
    and a take); cam0, cam1, ... in the given order where a recording has none."""
    serials = [i.serial_number for i in infos]
    for a, info in enumerate(infos):
        for b in range(a):
            if serials[a] is not None and serials[a] == serials[b]:
                raise ValueError(f"{infos[b].name} and {info.name} come from the same device "
                                 f"(serial {serials[a]}): give one recording per device")
    if all(s is not None and re.fullmatch(CAMERA_ID_PATTERN, s) for s in serials):
        return tuple(str(s) for s in serials)
    return tuple(f"cam{i}" for i in range(len(infos)))


def _check_same(infos: Sequence[RecordingInfo]) -> None:
    first = infos[0]
    for info in infos[1:]:
        if info.depth_mode != first.depth_mode:
            raise ValueError(f"{info.name}: depth mode {info.depth_mode} differs from "
                             f"{first.name}'s {first.depth_mode}; every recording of a capture "
                             "needs the same depth mode")
        if info.frame_period_us != first.frame_period_us:
            raise ValueError(f"{info.name}: {round(1e6 / info.frame_period_us)} fps differs "
                             f"from {first.name}'s {round(1e6 / first.frame_period_us)} fps")


def _sync_warnings(infos: Sequence[RecordingInfo]) -> tuple[str, ...]:
    if len(infos) < 2:
        return ()
    warnings = []
    standalone = [i.name for i in infos if i.sync_mode == "STANDALONE"]
    if standalone:
        warnings.append(f"{', '.join(standalone)}: recorded STANDALONE; devices share a clock "
                        "only over a sync cable, so frames matched by device timestamp may not "
                        "be of one instant")
    masters = [i.name for i in infos if i.sync_mode == "MASTER"]
    if len(masters) > 1:
        warnings.append(f"{', '.join(masters)}: more than one MASTER device")
    return tuple(warnings)


def _camera(camera_id: str, info: RecordingInfo) -> CameraInfo:
    depth = depth_intrinsics(info.calibration, info.depth_mode)
    if info.color_size_px is None:
        return CameraInfo(id=camera_id, depth_intrinsics=depth)
    return CameraInfo(id=camera_id, depth_intrinsics=depth,
                      color_intrinsics=color_intrinsics(info.calibration, info.color_size_px,
                                                        info.name),
                      color_from_depth=color_from_depth(info.calibration))


def open_recordings(paths: Sequence[str | Path], config: ImportConfig = ImportConfig()
                    ) -> Recordings:
    """Reads and checks every recording's header: the same depth mode and frame rate, one
    recording per device. ValueError of one line naming the file at fault."""
    if not paths:
        raise ValueError("no recordings given")
    infos = tuple(read_recording_info(p) for p in paths)
    _check_same(infos)
    ids = _camera_ids(infos)
    window = (config.sync_window_us if config.sync_window_us is not None
              else infos[0].frame_period_us // 2)
    if window < 0:
        raise ValueError(f"sync window: must be at least 0 us, got {window}")
    if config.writer_threads < 1:
        raise ValueError(f"writer threads: must be at least 1, got {config.writer_threads}")
    cameras = tuple(_camera(c, i) for c, i in zip(ids, infos, strict=True))
    return Recordings(infos, cameras, window, _sync_warnings(infos), config.writer_threads,
                      config.target)


def iter_frame_sets(recordings: Recordings) -> Iterator[FrameSet[CameraFrame]]:
    """Every frame of the recordings in frame-sets, in time order, complete or not (see
    pipeline.io.k4a_sync). A frame-set's timestamp is the master's trigger time."""
    def aligned(info: RecordingInfo) -> Generator[tuple[int, CameraFrame], None, None]:
        with closing(iter_camera_frames(info)) as frames:
            for frame in frames:
                yield frame.timestamp_us - info.subordinate_delay_us, frame

    streams = [aligned(info) for info in recordings.infos]
    try:
        for matched in match_frames(streams, lambda pair: pair[0], recordings.sync_window_us):
            frames = tuple(None if m is None else m[1] for m in matched.frames)
            yield FrameSet(matched.timestamp_us, frames, matched.dropped)
    finally:
        for stream in streams:  # closes the files of recordings not read to their ends
            stream.close()


def _depth_units(frame: CameraFrame) -> NDArray[np.uint16]:
    """(H, W) the recorded millimetres in their recorded byte order (big-endian, as PNG
    stores them, so the PNG writer copies them without a swap)."""
    width, height = frame.size_px
    return np.frombuffer(frame.depth_be, ">u2").reshape(height, width)


def recorded_view(camera: CameraInfo, index: int, frame: CameraFrame) -> StoredView:
    """The frame as the capture stores it: depth in the recorded millimetres (the capture's
    units, DEPTH_SCALE_M), an MJPG image as the recorded JPEG (no decode and re-encode)."""
    if frame.color is not None and frame.color.format == "MJPG":
        return StoredView(camera, index, _depth_units(frame), color_jpeg=frame.color.payload)
    color_rgb = frame.color.rgb() if frame.color is not None else None
    return StoredView(camera, index, _depth_units(frame), color_rgb=color_rgb)


def _write_views(out: Path, meta: CaptureMeta, views: Iterator[StoredView],
                 threads: int) -> None:
    """write_capture, or with ``threads`` writer threads encoding while this thread reads the
    recordings (see pipeline.io.capture_threads)."""
    if threads == 1:
        write_capture(out, meta, views)
        return
    write_capture_threaded(out, meta, views, threads)


def import_recordings(recordings: Recordings, out_dir: str | Path,
                      progress: Callable[[float], None] | None = None) -> ImportReport:
    """Writes the capture of ``recordings`` (see :func:`open_recordings`) to ``out_dir`` with
    :func:`pipeline.io.capture_io.write_capture`, one frame-set at a time. Cameras are in the
    order of the recordings; frames are numbered from 0 in time order. ``progress`` receives
    the fraction of the recordings' shared time done. ValueError of one line naming the file
    where a recording's data are refused, or where no frame-set is complete."""
    out = Path(out_dir)
    ids = tuple(c.id for c in recordings.cameras)
    first_us, last_us = recordings.shared_span_us()
    frames: list[FrameInfo] = []
    dropped = dict.fromkeys(ids, 0)
    counts = {"dropped": 0, "outside": 0, "missing_color": 0}

    def views() -> Generator[StoredView, None, None]:
        for frame_set in iter_frame_sets(recordings):
            if progress is not None and last_us > first_us:
                progress(min(max((frame_set.timestamp_us - first_us) / (last_us - first_us),
                                 0.0), 1.0))
            if not frame_set.complete:
                counts["dropped" if frame_set.dropped else "outside"] += 1
                for i in frame_set.dropped:
                    dropped[ids[i]] += 1
                continue
            index = len(frames)
            frames.append(FrameInfo(index=index, timestamp_us=max(frame_set.timestamp_us, 0)))
            for camera, info, frame in zip(recordings.cameras, recordings.infos,
                                           frame_set.frames, strict=True):
                assert frame is not None
                counts["missing_color"] += info.color_format is not None and frame.color is None
                yield recorded_view(camera, index, frame)

    meta = CaptureMeta(depth_scale=DEPTH_SCALE_M, cameras=recordings.cameras, frames=(),
                       target=recordings.target)
    with closing(views()) as stream:  # a failed write closes the recordings at once
        _write_views(out, meta, stream, recordings.writer_threads)
    if not frames:
        raise ValueError(f"no frame-set has a depth image of every recording within the "
                         f"{recordings.sync_window_us} us sync window ({counts['dropped']} "
                         f"incomplete, {counts['outside']} outside the time they share)")
    # capture.json again, now that the frames written are known
    write_capture(out, replace(meta, frames=tuple(frames)), ())
    if progress is not None:
        progress(1.0)
    return ImportReport(camera_ids=ids, frame_sets=len(frames), dropped=counts["dropped"],
                        dropped_by_camera=dropped, outside=counts["outside"],
                        missing_color=counts["missing_color"],
                        sync_window_us=recordings.sync_window_us,
                        frame_period_us=recordings.frame_period_us,
                        warnings=recordings.warnings)
