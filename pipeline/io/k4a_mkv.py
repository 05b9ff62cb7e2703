"""Azure Kinect recordings, as k4arecorder writes them, read with PyAV one frame at a time.

A recording is a Matroska file (Azure-Kinect-Sensor-SDK: src/record/sdk/record.cpp, and the
"Recording file format" page of its documentation) with

- video tracks named COLOR (MJPG, BGRA, NV12 or YUY2), DEPTH and IR; depth and IR are
  16-bit big-endian greyscale (FourCC ``b16g``), depth in millimetres, 0 = no measurement;
  each track carries a tag K4A_COLOR_TRACK / K4A_DEPTH_TRACK / K4A_IR_TRACK;
- tags: K4A_DEPTH_MODE (on the depth track), K4A_COLOR_MODE, K4A_WIRED_SYNC_MODE (MASTER,
  SUBORDINATE, STANDALONE), K4A_SUBORDINATE_DELAY_NS, K4A_DEPTH_DELAY_NS (depth's capture
  time after colour's), K4A_START_OFFSET_NS, K4A_DEVICE_SERIAL_NUMBER, and
  K4A_CALIBRATION_FILE naming the attachment that holds the device's calibration.json;
- block timestamps relative to the recording's start: a frame's device timestamp is its block
  timestamp plus the start offset. Devices on a sync cable share their clock, so device
  timestamps compare across recordings; a subordinate captures its delay after the master.

Every error is a ``ValueError`` of one line that names the file.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Generator, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import av
import cv2
import numpy as np
from numpy.typing import NDArray

from pipeline.io.k4a_calibration import DEPTH_MODES, DeviceCalibration, parse_calibration

DEPTH_UNIT_M = 0.001
"""Depth and IR pixels count millimetres."""
FRAME_RATES = (5, 15, 30)
SYNC_MODES = ("STANDALONE", "MASTER", "SUBORDINATE")
COLOR_FORMATS = ("MJPG", "BGRA", "NV12", "YUY2")
_RAW_BYTES_PER_PIXEL = {"BGRA": 4.0, "NV12": 1.5, "YUY2": 2.0}
_TO_RGB = {"BGRA": cv2.COLOR_BGRA2RGB, "NV12": cv2.COLOR_YUV2RGB_NV12,
           "YUY2": cv2.COLOR_YUV2RGB_YUY2}


@dataclass(frozen=True)
class RecordingInfo:
    """What a recording's header says, checked."""

    path: Path
    depth_mode: str
    depth_size_px: tuple[int, int]
    frame_period_us: int
    start_offset_us: int
    """Device timestamp of the recording's start (K4A_START_OFFSET_NS)."""
    duration_us: int
    sync_mode: str
    subordinate_delay_us: int
    """How long after the master's trigger this device captures (0 unless SUBORDINATE)."""
    depth_delay_us: int
    """Depth's capture time minus colour's on this device."""
    serial_number: str | None
    calibration: DeviceCalibration
    color_format: str | None
    """MJPG, BGRA, NV12 or YUY2; None without a colour track."""
    color_size_px: tuple[int, int] | None

    @property
    def name(self) -> str:
        return self.path.name


@dataclass(frozen=True)
class ColorImage:
    """One colour image as recorded."""

    timestamp_us: int
    format: str
    size_px: tuple[int, int]
    payload: bytes
    """A JPEG file (MJPG), or the raw pixels of the other formats."""

    def rgb(self) -> NDArray[np.uint8]:
        """(H, W, 3) RGB."""
        if self.format == "MJPG":
            bgr = cv2.imdecode(np.frombuffer(self.payload, np.uint8), cv2.IMREAD_COLOR)
            if bgr is None:
                raise ValueError(f"colour image at {self.timestamp_us} us: not a valid JPEG")
            return np.asarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
        width, height = self.size_px
        raw = np.frombuffer(self.payload, np.uint8)
        shape = {"BGRA": (height, width, 4), "NV12": (height * 3 // 2, width),
                 "YUY2": (height, width, 2)}[self.format]
        return np.asarray(cv2.cvtColor(raw.reshape(shape), _TO_RGB[self.format]))


@dataclass(frozen=True)
class CameraFrame:
    """One depth image of a device, with the colour image captured with it when there is one.
    Pixels stay as recorded until asked for, so frames that are skipped cost no conversion."""

    timestamp_us: int
    """The depth image's device timestamp."""
    size_px: tuple[int, int]
    depth_be: bytes | memoryview
    """Depth as recorded: 16-bit big-endian millimetres, row-major (read-only; a view of the
    demuxed packet where read from a recording)."""
    color: ColorImage | None

    def depth_mm(self) -> NDArray[np.uint16]:
        """(H, W) millimetres, 0 = no measurement."""
        width, height = self.size_px
        return np.frombuffer(self.depth_be, ">u2").reshape(height, width).astype(np.uint16)

    def depth_m(self) -> NDArray[np.float32]:
        """(H, W) metres, 0 = no measurement (one conversion from the recorded bytes)."""
        width, height = self.size_px
        depth = np.frombuffer(self.depth_be, ">u2").reshape(height, width).astype(np.float32)
        depth *= np.float32(DEPTH_UNIT_M)
        return depth


def _tags(metadata: Mapping[str, str]) -> dict[str, str]:
    """Matroska tags by name: FFmpeg appends '-<language>' to tags that have one."""
    return {key.split("-", 1)[0].upper(): value for key, value in metadata.items()}


def _open(path: Path) -> Any:
    """An opened Matroska input container, or ValueError naming the file."""
    if not path.is_file():
        raise ValueError(f"{path}: no such recording")
    try:
        container = av.open(str(path))
    except (av.error.FFmpegError, OSError) as exc:
        raise ValueError(f"{path.name}: not a readable Matroska recording (truncated or not "
                         f"Matroska: {exc.strerror or exc})") from None
    if "matroska" not in container.format.name:
        container.close()
        raise ValueError(f"{path.name}: not a Matroska file ({container.format.long_name})")
    return container


def _track(container: Any, name: str) -> Any:
    """The video stream k4arecorder named ``name`` (COLOR, DEPTH, IR), or None."""
    for stream in container.streams.video:
        tags = _tags(stream.metadata)
        if f"K4A_{name}_TRACK" in tags or tags.get("TITLE") == name:
            return stream
    return None


def _calibration(container: Any, tags: Mapping[str, str], name: str) -> DeviceCalibration:
    """The calibration attachment: the one K4A_CALIBRATION_FILE names, else calibration.json."""
    wanted = tags.get("K4A_CALIBRATION_FILE", "calibration.json")
    for stream in container.streams:
        if stream.type != "attachment":
            continue
        stream_tags = _tags(stream.metadata)
        if "K4A_CALIBRATION_FILE" in stream_tags or stream_tags.get("FILENAME") == wanted:
            return parse_calibration(bytes(stream.data), name)
    raise ValueError(f"{name}: no calibration attachment ({wanted}): not recorded from a "
                     "device, or written by a tool that dropped it")


def _int_tag(tags: Mapping[str, str], key: str, name: str, divisor: int = 1000) -> int:
    """An integer tag (0 when absent), divided by ``divisor`` (ns to us by default)."""
    value = tags.get(key, "0")
    try:
        return int(value) // divisor
    except ValueError:
        raise ValueError(f"{name}: tag {key} is {value!r}, not an integer") from None


def _frame_period_us(stream: Any, name: str) -> int:
    rate = stream.average_rate or stream.guessed_rate
    fps = round(float(rate)) if rate else 0
    if fps not in FRAME_RATES:
        raise ValueError(f"{name}: frame rate {float(rate or 0):g} fps, the device records at "
                         f"{', '.join(map(str, FRAME_RATES))} fps")
    return round(1_000_000 / fps)


def _depth_mode(tags: Mapping[str, str], depth: Any, name: str) -> str:
    mode = tags.get("K4A_DEPTH_MODE", "").upper()
    if not mode:
        raise ValueError(f"{name}: no K4A_DEPTH_MODE tag: not an Azure Kinect recording")
    if mode not in DEPTH_MODES:
        raise ValueError(f"{name}: unknown depth mode {mode!r} (one of {', '.join(DEPTH_MODES)})")
    if depth is None:
        raise ValueError(f"{name}: no depth track (depth mode {mode})")
    size = (depth.codec_context.width, depth.codec_context.height)
    if size != DEPTH_MODES[mode].image_px:
        raise ValueError(f"{name}: depth images of {size[0]}x{size[1]} do not match depth mode "
                         f"{mode}")
    if depth.codec_context.codec_tag != "b16g":
        raise ValueError(f"{name}: the depth track's format is {depth.codec_context.codec_tag!r}, "
                         "not 16-bit greyscale (b16g)")
    return mode


def _color_format(color: Any, name: str) -> str:
    codec = color.codec_context
    fmt = "MJPG" if codec.name == "mjpeg" else str(codec.codec_tag)
    if fmt not in COLOR_FORMATS:
        raise ValueError(f"{name}: colour format {fmt!r} is not one the device records "
                         f"({', '.join(COLOR_FORMATS)})")
    return fmt


def read_recording_info(path: str | Path) -> RecordingInfo:
    """Opens a recording, reads and checks its header, and closes it."""
    path = Path(path)
    container = _open(path)
    try:
        return _info(container, path)
    finally:
        container.close()


def _info(container: Any, path: Path) -> RecordingInfo:
    name = path.name
    depth, color = _track(container, "DEPTH"), _track(container, "COLOR")
    tags = _tags(container.metadata) | (_tags(depth.metadata) if depth is not None else {})
    mode = _depth_mode(tags, depth, name)
    sync_mode = tags.get("K4A_WIRED_SYNC_MODE", "STANDALONE").upper()
    if sync_mode not in SYNC_MODES:
        raise ValueError(f"{name}: unknown K4A_WIRED_SYNC_MODE {sync_mode!r}")
    if container.duration is None:
        raise ValueError(f"{name}: truncated: the recording has no duration (its recorder did "
                         "not close it)")
    color_format = _color_format(color, name) if color is not None else None
    return RecordingInfo(
        path=path, depth_mode=mode, depth_size_px=DEPTH_MODES[mode].image_px,
        frame_period_us=_frame_period_us(depth, name),
        start_offset_us=_int_tag(tags, "K4A_START_OFFSET_NS", name),
        duration_us=int(container.duration),  # AV_TIME_BASE is microseconds
        sync_mode=sync_mode,
        subordinate_delay_us=(_int_tag(tags, "K4A_SUBORDINATE_DELAY_NS", name)
                              if sync_mode == "SUBORDINATE" else 0),
        depth_delay_us=_int_tag(tags, "K4A_DEPTH_DELAY_NS", name),
        serial_number=tags.get("K4A_DEVICE_SERIAL_NUMBER") or None,
        calibration=_calibration(container, tags, name),
        color_format=color_format,
        color_size_px=(None if color is None
                       else (color.codec_context.width, color.codec_context.height)))


def _block_us(packet: Any) -> int:
    """The packet's timestamp in microseconds (k4arecorder: exact; FFmpeg: milliseconds)."""
    base = packet.time_base
    return int(packet.pts * base.numerator * 1_000_000 // base.denominator)


def _check_payload(info: RecordingInfo, payload: bytes | memoryview, kind: str,
                   at_us: int) -> None:
    """ValueError where a frame's bytes cannot be the image its track declares."""
    if kind == "depth":
        expected = info.depth_size_px[0] * info.depth_size_px[1] * 2
    elif info.color_format == "MJPG":
        if payload[:2] != b"\xff\xd8":
            raise ValueError(f"{info.name}: colour frame at {at_us} us is not a JPEG image")
        return
    else:
        assert info.color_size_px is not None and info.color_format is not None
        width, height = info.color_size_px
        expected = math.ceil(width * height * _RAW_BYTES_PER_PIXEL[info.color_format])
    if len(payload) != expected:
        raise ValueError(f"{info.name}: {kind} frame at {at_us} us has {len(payload)} bytes, "
                         f"{expected} expected (damaged or truncated)")


class _ColorPairing:
    """Pairs each depth image with the colour image of the same capture: the one nearest to
    the depth's timestamp less the depth delay, within half a frame period. Packets arrive in
    timestamp order up to a cluster, so a depth image is settled once a packet a frame period
    past its window has arrived; holding only those pending bounds the memory to a few
    frames."""

    def __init__(self, info: RecordingInfo) -> None:
        self.info = info
        self.tolerance_us = info.frame_period_us // 2
        self.slack_us = self.tolerance_us + info.frame_period_us
        self.depth: deque[tuple[int, bytes | memoryview]] = deque()
        self.color: deque[ColorImage] = deque()

    def settled(self, newest_us: int, at_end: bool = False) -> Iterator[CameraFrame]:
        while self.depth and (at_end or self.info.color_format is None
                              or newest_us > self._color_time(self.depth[0][0]) + self.slack_us):
            timestamp, payload = self.depth.popleft()
            yield CameraFrame(timestamp, self.info.depth_size_px, payload,
                              self._take_color(self._color_time(timestamp)))
        # Colour older than any pending or future depth's window can never be taken.
        oldest_us = (self._color_time(self.depth[0][0]) if self.depth
                     else newest_us - self.slack_us)
        while self.color and self.color[0].timestamp_us < oldest_us - self.tolerance_us:
            self.color.popleft()

    def _color_time(self, depth_us: int) -> int:
        return depth_us - self.info.depth_delay_us

    def _take_color(self, wanted_us: int) -> ColorImage | None:
        while self.color and self.color[0].timestamp_us < wanted_us - self.tolerance_us:
            self.color.popleft()
        near = [c for c in self.color if abs(c.timestamp_us - wanted_us) <= self.tolerance_us]
        if not near:
            return None
        best = min(near, key=lambda c: abs(c.timestamp_us - wanted_us))
        while self.color and self.color[0].timestamp_us <= best.timestamp_us:
            self.color.popleft()
        return best


def iter_camera_frames(info: RecordingInfo) -> Generator[CameraFrame, None, None]:
    """The recording's depth images in order, each with its colour image when there is one.
    One frame at a time; the file stays open until the iterator ends or is closed. Raises
    ValueError naming the file where its data are damaged or end before its duration."""
    container = _open(info.path)
    try:
        depth, color = _track(container, "DEPTH"), _track(container, "COLOR")
        pairing = _ColorPairing(info)
        last_depth_us, newest_us = -1, 0
        try:
            for packet in container.demux([s for s in (depth, color) if s is not None]):
                if packet.size == 0 or packet.pts is None:  # the demuxer's end-of-stream marks
                    continue
                block_us = _block_us(packet)
                timestamp = info.start_offset_us + block_us
                if packet.stream.index == depth.index:
                    # The packet's own bytes, not a copy: depth is most of what is read.
                    depth_be = memoryview(packet).toreadonly()
                    _check_payload(info, depth_be, "depth", timestamp)
                    pairing.depth.append((timestamp, depth_be))
                    last_depth_us = max(last_depth_us, block_us)
                else:
                    payload = bytes(packet)
                    _check_payload(info, payload, "colour", timestamp)
                    assert info.color_format is not None and info.color_size_px is not None
                    pairing.color.append(ColorImage(timestamp, info.color_format,
                                                    info.color_size_px, payload))
                newest_us = max(newest_us, timestamp)
                yield from pairing.settled(newest_us)
        except av.error.FFmpegError as exc:
            raise ValueError(f"{info.name}: damaged Matroska data ({exc.strerror or exc})"
                             ) from None
        yield from pairing.settled(0, at_end=True)
    finally:
        container.close()
    _check_complete(info, last_depth_us)


def _check_complete(info: RecordingInfo, last_depth_us: int) -> None:
    """ValueError where the depth frames end well before the duration the header declares:
    the file lost its end. k4arecorder's duration is its last block's time (IMU samples may
    follow the last depth image by up to a frame period)."""
    if last_depth_us < 0:
        raise ValueError(f"{info.name}: no depth frames (truncated or empty recording)")
    if last_depth_us < info.duration_us - 2 * info.frame_period_us:
        raise ValueError(f"{info.name}: truncated: its depth frames end at "
                         f"{last_depth_us / 1e6:.3f} s of the {info.duration_us / 1e6:.3f} s "
                         "its header declares")
