"""Azure Kinect recordings for the tests and the import benchmark, written with PyAV in the
layout k4arecorder writes (Azure-Kinect-Sensor-SDK, src/record/sdk/record.cpp):

- tracks named COLOR (MJPG or BGRA), DEPTH and IR (16-bit big-endian greyscale, FourCC
  ``b16g``), each tagged with K4A_<NAME>_TRACK, the depth track with K4A_DEPTH_MODE and the
  colour track with K4A_COLOR_MODE;
- global tags K4A_WIRED_SYNC_MODE, K4A_SUBORDINATE_DELAY_NS, K4A_DEPTH_DELAY_NS,
  K4A_START_OFFSET_NS and K4A_DEVICE_SERIAL_NUMBER;
- the device calibration as the attachment ``calibration.json``, named by the tag
  K4A_CALIBRATION_FILE on that attachment.

Where FFmpeg's Matroska muxer writes differently from libmatroska in k4arecorder:

- timestamps are in milliseconds (k4arecorder: microseconds), so the writer puts frames on
  whole milliseconds and the start offset (a tag, in nanoseconds) carries the finer part;
- MJPG colour is stored as ``V_MJPEG`` (k4arecorder: ``V_MS/VFW/FOURCC`` with FourCC MJPG);
  both demux to the same JPEG packets;
- raw video is stored as ``V_MS/VFW/FOURCC`` only with the muxer's ``allow_raw_vfw`` option,
  and the muxer clears the FourCC of raw video it does not know; the writer puts the
  BITMAPINFOHEADER back as k4arecorder writes it (same 40 bytes, so no size changes) with
  ``b16g`` or ``BGRA``.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import Any

import av
import cv2
import numpy as np
from numpy.typing import NDArray

DEPTH_SIZES = {"NFOV_2X2BINNED": (320, 288), "NFOV_UNBINNED": (640, 576),
               "WFOV_2X2BINNED": (512, 512), "WFOV_UNBINNED": (1024, 1024),
               "PASSIVE_IR": (1024, 1024)}
_MS = Fraction(1, 1000)

# A plausible device calibration (values of the order of a real Azure Kinect's): normalised
# Brown-Conrady parameters [cx, cy, fx, fy, k1..k6, codx, cody, p2, p1], rotations row-major,
# translations in metres.
DEPTH_PARAMS = (0.5007, 0.5063, 0.4913, 0.4914, 0.4862, -0.0723, -0.0021, 0.8284, 0.0512,
                -0.0125, 0.0, 0.0, -4.1e-05, -8.2e-05)
COLOR_PARAMS = (0.4997, 0.5040, 0.4602, 0.6137, 0.0801, -0.0551, 0.0143, 0.0, 0.0, 0.0,
                0.0, 0.0, 0.00037, 0.00089)
COLOR_ROTATION = tuple(float(v) for v in cv2.Rodrigues(np.array([-0.0721, -0.0033, -0.0050]))[0]
                       .ravel())  # about 4 degrees, mostly about x
COLOR_TRANSLATION_M = (-0.032045, -0.001945, 0.003876)


def calibration_json(depth_rotation: tuple[float, ...] = (1, 0, 0, 0, 1, 0, 0, 0, 1),
                     depth_translation_m: tuple[float, ...] = (0.0, 0.0, 0.0),
                     color_sensor: tuple[int, int] = (4096, 3072)) -> bytes:
    """calibration.json as the device stores it: one depth (D0) and one colour (PV0) camera."""
    def camera(location: str, params: tuple[float, ...], size: tuple[int, int],
               rotation: tuple[float, ...], translation: tuple[float, ...]) -> dict[str, Any]:
        return {"Intrinsics": {"ModelParameterCount": len(params),
                               "ModelParameters": list(params),
                               "ModelType": "CALIBRATION_LensDistortionModelBrownConrady"},
                "Location": location, "MetricRadius": 1.7,
                "Rt": {"Rotation": list(rotation), "Translation": list(translation)},
                "SensorHeight": size[1], "SensorWidth": size[0],
                "Shutter": "CALIBRATION_ShutterTypeUndefined",
                "ThermalAdjustmentParams": {"Params": [0.0] * 12}}

    cameras = [camera("CALIBRATION_CameraLocationD0", DEPTH_PARAMS, (1024, 1024), depth_rotation,
                      depth_translation_m),
               camera("CALIBRATION_CameraLocationPV0", COLOR_PARAMS, color_sensor,
                      COLOR_ROTATION, COLOR_TRANSLATION_M)]
    return json.dumps({"CalibrationInformation": {"Cameras": cameras, "InertialSensors": [],
                                                  "Metadata": {"SerialId": "", "Version": {
                                                      "Major": 1, "Minor": 2}}}}).encode()


def depth_image_mm(width: int, height: int, frame: int, seed: int = 0) -> NDArray[np.uint16]:
    """(H, W) depth in millimetres that changes per pixel, frame and device, with holes (0)
    and values above 32767 so that byte order and sign mistakes show."""
    y, x = np.mgrid[0:height, 0:width].astype(np.int64)
    mm = (400 + 7 * x + 13 * y + 101 * frame + 977 * seed) % 40000
    mm[(x + 3 * y + frame) % 17 == 0] = 0
    mm[0, 0] = 65535 - frame
    return mm.astype(np.uint16)


def color_image_bgr(width: int, height: int, frame: int) -> NDArray[np.uint8]:
    """(H, W, 3) a smooth colour picture that changes per frame (JPEG keeps it close)."""
    y, x = np.mgrid[0:height, 0:width]
    image = np.stack([(x * 255) // max(width - 1, 1), (y * 255) // max(height - 1, 1),
                      np.full_like(x, (frame * 37) % 256)], axis=-1)
    return image.astype(np.uint8)


@dataclass(frozen=True)
class RecordingSpec:
    """What one recording holds. Frames are numbered from 0 at the recording's frame rate;
    frame k's device timestamp is start_offset_ns / 1000 + k * period on whole milliseconds."""

    depth_mode: str = "NFOV_UNBINNED"
    color: str | None = "MJPG"
    """MJPG, BGRA, NV12 or None (no colour track)."""
    color_size: tuple[int, int] = (1280, 720)
    fps: int = 30
    frame_count: int = 6
    start_offset_ns: int = 1_000_000_000
    sync_mode: str = "STANDALONE"
    subordinate_delay_ns: int = 0
    serial: str | None = "000000000001"
    calibration: bytes | None = field(default_factory=calibration_json)
    dropped_depth: frozenset[int] = frozenset()
    dropped_color: frozenset[int] = frozenset()
    depth_delay_ns: int = 0
    """Depth's capture time after colour's: colour blocks sit this much earlier (whole ms)."""
    ir: bool = True
    seed: int = 0
    """Picks the depth values (see depth_image_mm)."""
    distinct_colors: int = 0
    """0: every colour frame its own picture; n: frames reuse n JPEGs (faster to write)."""

    def block_ms(self, frame: int) -> int:
        return (frame * 1000) // self.fps

    def device_timestamp_us(self, frame: int) -> int:
        return self.start_offset_ns // 1000 + self.block_ms(frame) * 1000


def _bitmap_header(width: int, height: int, bits: int, fourcc: bytes) -> bytes:
    return struct.pack("<IiiHH4sIiiII", 40, width, height, 1, bits, fourcc,
                       width * height * bits // 8, 0, 0, 0, 0)


def _restore_fourcc(path: Path, width: int, height: int, bits: int, fourcc: bytes) -> None:
    """Rewrites FFmpeg's BITMAPINFOHEADER of a raw track of this size (no FourCC, a guessed bit
    count, rows top-down as a negative height) as k4arecorder writes it; the same 40 bytes, so
    the file's structure stays."""
    data = bytearray(path.read_bytes())
    ffmpeg_head = struct.pack("<IiiH", 40, width, -height, 1)
    start, found = 0, 0
    while (at := data.find(ffmpeg_head, start)) >= 0:
        data[at:at + 40] = _bitmap_header(width, height, bits, fourcc)
        found += 1
        start = at + 40
    if not found:
        raise RuntimeError(f"{path}: no {width}x{height} {bits}-bit bitmap header to rewrite")
    path.write_bytes(bytes(data))


def _video_stream(out: Any, codec: str, name: str, size: tuple[int, int], fps: int) -> Any:
    stream = out.add_mux_stream(codec, rate=fps, width=size[0], height=size[1])
    stream.time_base = _MS
    stream.metadata["title"] = name
    # k4arecorder's value is the track's UID, which FFmpeg draws itself; readers look for
    # the tag on the track, not at its value.
    stream.metadata[f"K4A_{name}_TRACK"] = str(stream.index + 1)
    return stream


def _mux(out: Any, stream: Any, payload: bytes, block_ms: int) -> None:
    packet = av.Packet(payload)
    packet.stream = stream
    packet.pts = packet.dts = block_ms
    packet.time_base = _MS
    out.mux(packet)


def write_recording(path: str | Path, spec: RecordingSpec,
                    depth_mm: Callable[[int], NDArray[np.uint16]] | None = None,
                    color_bgr: Callable[[int], NDArray[np.uint8]] | None = None) -> Path:
    """Writes ``spec`` to ``path`` (.mkv). Depth of frame k is ``depth_mm(k)`` (default:
    depth_image_mm of the mode's size and spec.seed), IR the depth's complement, colour
    ``color_bgr(k)`` (default: color_image_bgr)."""
    path = Path(path)
    width, height = DEPTH_SIZES[spec.depth_mode]
    depth_of = depth_mm or (lambda k: depth_image_mm(width, height, k, spec.seed))
    color_of = color_bgr or (lambda k: color_image_bgr(*spec.color_size, k))
    out = av.open(str(path), "w", format="matroska",
                  options={"allow_raw_vfw": "1", "write_crc32": "0"})
    color = None
    if spec.color is not None:
        color = _video_stream(out, "mjpeg" if spec.color == "MJPG" else "rawvideo", "COLOR",
                              spec.color_size, spec.fps)
        color.metadata["K4A_COLOR_MODE"] = f"{spec.color}_{spec.color_size[1]}P"
    depth = None
    if spec.depth_mode != "PASSIVE_IR":
        depth = _video_stream(out, "rawvideo", "DEPTH", (width, height), spec.fps)
        depth.metadata["K4A_DEPTH_MODE"] = spec.depth_mode
    else:
        out.metadata["K4A_DEPTH_MODE"] = spec.depth_mode
    ir = _video_stream(out, "rawvideo", "IR", (width, height), spec.fps) if spec.ir else None
    if ir is not None:
        ir.metadata["K4A_IR_MODE"] = "PASSIVE" if spec.depth_mode == "PASSIVE_IR" else "ACTIVE"
    _global_tags(out, spec)
    if spec.calibration is not None:
        attached = out.add_attachment("calibration.json", "application/octet-stream",
                                      spec.calibration)
        attached.metadata["K4A_CALIBRATION_FILE"] = "calibration.json"
    jpegs: dict[int, bytes] = {}
    for k in range(spec.frame_count):
        block = spec.block_ms(k)
        if color is not None and k not in spec.dropped_color:
            _mux(out, color, _color_payload(spec, k, color_of, jpegs),
                 block - spec.depth_delay_ns // 1_000_000)
        if k not in spec.dropped_depth:
            mm = depth_of(k)
            if depth is not None:
                _mux(out, depth, mm.astype(">u2").tobytes(), block)
            if ir is not None:
                _mux(out, ir, (65535 - mm).astype(">u2").tobytes(), block)
    out.close()
    if depth is not None or ir is not None:
        _restore_fourcc(path, width, height, 16, b"b16g")
    if spec.color in ("BGRA", "NV12"):
        _restore_fourcc(path, *spec.color_size, 32 if spec.color == "BGRA" else 12,
                        spec.color.encode())
    return path


def _global_tags(out: Any, spec: RecordingSpec) -> None:
    out.metadata["K4A_WIRED_SYNC_MODE"] = spec.sync_mode
    if spec.sync_mode == "SUBORDINATE":
        out.metadata["K4A_SUBORDINATE_DELAY_NS"] = str(spec.subordinate_delay_ns)
    if spec.color is not None and spec.depth_mode != "PASSIVE_IR":
        out.metadata["K4A_DEPTH_DELAY_NS"] = str(spec.depth_delay_ns)
    out.metadata["K4A_START_OFFSET_NS"] = str(spec.start_offset_ns)
    if spec.serial is not None:
        out.metadata["K4A_DEVICE_SERIAL_NUMBER"] = spec.serial


def _color_payload(spec: RecordingSpec, frame: int,
                   color_of: Callable[[int], NDArray[np.uint8]], cache: dict[int, bytes]) -> bytes:
    key = frame % spec.distinct_colors if spec.distinct_colors else frame
    if key not in cache:
        bgr = color_of(key)
        if spec.color == "MJPG":
            ok, jpeg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 90])
            assert ok
            payload = jpeg.tobytes()
        elif spec.color == "NV12":  # the Y plane, then U and V interleaved at quarter size
            planar = cv2.cvtColor(bgr, cv2.COLOR_BGR2YUV_I420)
            height = bgr.shape[0]
            u = planar[height:height + height // 4].ravel()
            v = planar[height + height // 4:].ravel()
            payload = planar[:height].tobytes() + np.stack([u, v], axis=-1).tobytes()
        else:
            payload = cv2.cvtColor(bgr, cv2.COLOR_BGR2BGRA).tobytes()
        if not spec.distinct_colors:
            return payload
        cache[key] = payload
    return cache[key]


def calibration_json_of(depth: Any, color: Any, color_from_depth: NDArray[np.float64]) -> bytes:
    """calibration.json whose NFOV_UNBINNED depth and 720p colour modes have these pixel
    intrinsics (pipeline.capture.Intrinsics, OpenCV distortion) and this colour-from-depth:
    the SDK's mode rules run backwards, the depth camera as the reference."""
    def params(intr: Any, binned: tuple[int, int], crop: tuple[int, int]) -> tuple[float, ...]:
        k1, k2, p1, p2, k3, k4, k5, k6 = intr.distortion_coeffs()
        return ((intr.cx + 0.5 + crop[0]) / binned[0], (intr.cy + 0.5 + crop[1]) / binned[1],
                intr.fx / binned[0], intr.fy / binned[1], k1, k2, k3, k4, k5, k6, 0.0, 0.0,
                p2, p1)

    assert (depth.width, depth.height, color.width, color.height) == (640, 576, 1280, 720)
    document = json.loads(calibration_json())
    depth_cam, color_cam = document["CalibrationInformation"]["Cameras"]
    depth_cam["Intrinsics"]["ModelParameters"] = list(params(depth, (1024, 1024), (192, 180)))
    color_cam["Intrinsics"]["ModelParameters"] = list(params(color, (1280, 960), (0, 120)))
    color_cam["Rt"] = {"Rotation": np.asarray(color_from_depth)[:3, :3].ravel().tolist(),
                       "Translation": np.asarray(color_from_depth)[:3, 3].tolist()}
    return json.dumps(document).encode()


_RIG_WIDTH, _RIG_HEIGHT = 640, 576
_NOISE_FIELDS = 8


def _rig_scene(seed: int) -> tuple[NDArray[np.float64], list[NDArray[np.float64]],
                                   list[NDArray[np.bool_]]]:
    """A sphere in front of a wall (mm), noise fields (sigma 2 mm) and hole masks to cycle."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:_RIG_HEIGHT, 0:_RIG_WIDTH].astype(np.float64)
    r2 = ((x - _RIG_WIDTH / 2) ** 2 + (y - _RIG_HEIGHT / 2) ** 2) / (_RIG_HEIGHT / 3) ** 2
    base = np.where(r2 < 1.0, 1500.0 - 400.0 * np.sqrt(np.clip(1.0 - r2, 0, 1)), 3000.0)
    noise = [rng.normal(0.0, 2.0, base.shape) for _ in range(_NOISE_FIELDS)]
    holes = [rng.random(base.shape) < 0.05 for _ in range(_NOISE_FIELDS)]
    return base, noise, holes


def rig_recordings(folder: Path, cameras: int, seconds: int) -> list[Path]:
    """One NFOV_UNBINNED recording per device of a synchronised rig (a master, subordinates
    160 us apart), ``seconds`` at 30 fps: depth a noisy surface with holes, so that its PNGs
    cost what real depth's do, and colour noisy 1280x720 JPEGs of real-world size."""
    frames = seconds * 30
    rng = np.random.default_rng(0)
    pictures = [np.clip(cv2.GaussianBlur(rng.integers(0, 256, (720, 1280, 3)).astype(np.uint8),
                                         (0, 0), 1.5).astype(int) + 40 * i, 0, 255)
                .astype(np.uint8) for i in range(6)]
    paths = []
    for device in range(cameras):
        base, noise, holes = _rig_scene(device)

        def depth(k: int, base: Any = base, noise: Any = noise, holes: Any = holes
                  ) -> NDArray[np.uint16]:
            mm = base + 3.0 * np.sin(k / 10.0) + noise[k % _NOISE_FIELDS]
            mm[holes[(k * 3) % _NOISE_FIELDS]] = 0
            return np.rint(mm).astype(np.uint16)

        spec = RecordingSpec(
            depth_mode="NFOV_UNBINNED", frame_count=frames, distinct_colors=len(pictures),
            sync_mode="MASTER" if device == 0 else "SUBORDINATE",
            subordinate_delay_ns=160_000 * device, serial=f"{device + 1:012d}",
            start_offset_ns=1_000_000_000 + 160_000 * device)
        paths.append(write_recording(folder / f"device{device}.mkv", spec, depth,
                                     lambda k: pictures[k % len(pictures)]))
    return paths
