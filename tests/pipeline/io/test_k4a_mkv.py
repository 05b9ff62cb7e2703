"""Azure Kinect recordings: header, calibration per mode, frames, and refusals of one line."""

from __future__ import annotations

import json
from pathlib import Path

import av
import cv2
import numpy as np
import pytest

from pipeline.io.k4a_calibration import (
    color_from_depth,
    color_intrinsics,
    depth_intrinsics,
    parse_calibration,
)
from pipeline.io.k4a_mkv import iter_camera_frames, read_recording_info
from tests.k4a_recordings import (
    COLOR_PARAMS,
    DEPTH_PARAMS,
    DEPTH_SIZES,
    RecordingSpec,
    calibration_json,
    color_image_bgr,
    depth_image_mm,
    write_recording,
)

SMALL = dict(depth_mode="NFOV_2X2BINNED", frame_count=5)


def _one_line_error(path: Path, call: object) -> str:
    with pytest.raises(ValueError) as caught:
        call()  # type: ignore[operator]
    message = str(caught.value)
    assert "\n" not in message and path.name in message, message
    return message


def test_header_gives_mode_sync_role_offsets_serial_and_colour(tmp_path: Path) -> None:
    spec = RecordingSpec(**SMALL, sync_mode="SUBORDINATE", subordinate_delay_ns=160_000,
                         start_offset_ns=2_345_678_000, serial="000123456789", fps=15)
    info = read_recording_info(write_recording(tmp_path / "sub.mkv", spec))
    assert (info.depth_mode, info.depth_size_px) == ("NFOV_2X2BINNED", (320, 288))
    assert info.frame_period_us == 66667
    assert (info.sync_mode, info.subordinate_delay_us) == ("SUBORDINATE", 160)
    assert info.start_offset_us == 2_345_678
    assert info.serial_number == "000123456789"
    assert (info.color_format, info.color_size_px) == ("MJPG", (1280, 720))
    assert info.duration_us >= spec.block_ms(4) * 1000


# The Sensor SDK's mode table (mode_specific_calibration.c): binned sensor, crop, image.
SDK_DEPTH_MODES = {"NFOV_2X2BINNED": ((512, 512), (96, 90)),
                   "NFOV_UNBINNED": ((1024, 1024), (192, 180)),
                   "WFOV_2X2BINNED": ((512, 512), (0, 0)),
                   "WFOV_UNBINNED": ((1024, 1024), (0, 0))}


@pytest.mark.parametrize("mode", sorted(SDK_DEPTH_MODES))
def test_depth_intrinsics_of_each_mode_follow_the_sdk(mode: str) -> None:
    (bw, bh), (ox, oy) = SDK_DEPTH_MODES[mode]
    cx, cy, fx, fy = DEPTH_PARAMS[:4]
    got = depth_intrinsics(parse_calibration(calibration_json(), "x.mkv"), mode)
    assert (got.width, got.height) == DEPTH_SIZES[mode]
    assert got.fx == pytest.approx(fx * bw) and got.fy == pytest.approx(fy * bh)
    assert got.cx == pytest.approx(cx * bw - ox - 0.5)
    assert got.cy == pytest.approx(cy * bh - oy - 0.5)


def test_distortion_is_opencv_rational_order() -> None:
    got = depth_intrinsics(parse_calibration(calibration_json(), "x.mkv"), "NFOV_UNBINNED")
    k1, k2, k3, k4, k5, k6, _codx, _cody, p2, p1 = DEPTH_PARAMS[4:14]
    assert got.distortion == (k1, k2, p1, p2, k3, k4, k5, k6)


@pytest.mark.parametrize(("size", "binned", "crop_y"), [
    ((1280, 720), (1280, 960), 120), ((1920, 1080), (1920, 1440), 180),
    ((2048, 1536), (2048, 1536), 0), ((4096, 3072), (4096, 3072), 0)])
def test_colour_intrinsics_of_each_resolution_follow_the_sdk(
        size: tuple[int, int], binned: tuple[int, int], crop_y: int) -> None:
    cx, cy, fx, fy = COLOR_PARAMS[:4]
    got = color_intrinsics(parse_calibration(calibration_json(), "x.mkv"), size, "x.mkv")
    assert (got.width, got.height) == size
    assert got.fx == pytest.approx(fx * binned[0]) and got.fy == pytest.approx(fy * binned[1])
    assert got.cx == pytest.approx(cx * binned[0] - 0.5)
    assert got.cy == pytest.approx(cy * binned[1] - crop_y - 0.5)


def test_a_16_by_9_colour_calibration_is_read_as_the_4_by_3_sensor() -> None:
    legacy = parse_calibration(calibration_json(color_sensor=(4096, 2304)), "x.mkv")
    got = color_intrinsics(legacy, (1920, 1080), "x.mkv")
    cx, cy, fx, fy = COLOR_PARAMS[:4]
    # 4096x2304 is the 4:3 sensor less 384 rows at top and bottom: same pixels, shifted rows.
    assert got.fx == pytest.approx(fx * 1920) and got.fy == pytest.approx(fy * 2304 * 1440 / 3072)
    assert got.cx == pytest.approx(cx * 1920 - 0.5)
    assert got.cy == pytest.approx((cy * 2304 + 384) / 3072 * 1440 - 180 - 0.5)


def test_colour_from_depth_composes_the_two_cameras_extrinsics() -> None:
    angle = np.deg2rad(6.0)
    rotation = (np.cos(angle), 0.0, np.sin(angle), 0.0, 1.0, 0.0, -np.sin(angle), 0.0,
                np.cos(angle))
    calibration = parse_calibration(
        calibration_json(depth_rotation=rotation, depth_translation_m=(0.01, -0.02, 0.03)),
        "x.mkv")
    got = color_from_depth(calibration)
    point_depth = np.array([0.1, -0.2, 1.5, 1.0])
    # a point in the depth frame, to the reference frame, to the colour frame
    point_reference = np.linalg.solve(calibration.depth.camera_from_reference, point_depth)
    expected = calibration.color.camera_from_reference @ point_reference  # type: ignore[union-attr]
    assert got @ point_depth == pytest.approx(expected)
    assert got[:3, :3].T @ got[:3, :3] == pytest.approx(np.eye(3))


def test_frames_have_exact_millimetres_and_their_own_colour(tmp_path: Path) -> None:
    spec = RecordingSpec(**SMALL, dropped_depth=frozenset({2}), dropped_color=frozenset({3}),
                         start_offset_ns=5_000_123_000, seed=3)
    info = read_recording_info(write_recording(tmp_path / "a.mkv", spec))
    frames = list(iter_camera_frames(info))
    kept = [k for k in range(spec.frame_count) if k not in spec.dropped_depth]
    assert [f.timestamp_us for f in frames] == [spec.device_timestamp_us(k) for k in kept]
    for k, frame in zip(kept, frames, strict=True):
        assert np.array_equal(frame.depth_mm(), depth_image_mm(320, 288, k, seed=3))
        if k in spec.dropped_color:
            assert frame.color is None
            continue
        assert frame.color is not None and frame.color.payload[:2] == b"\xff\xd8"
        expected = cv2.cvtColor(color_image_bgr(1280, 720, k), cv2.COLOR_BGR2RGB)
        assert np.abs(frame.color.rgb().astype(int) - expected).mean() < 3


def test_colour_is_paired_across_the_depth_delay(tmp_path: Path) -> None:
    # depth captured 12 ms before colour: each colour block sits 12 ms after its depth
    spec = RecordingSpec(**SMALL, depth_delay_ns=-12_000_000, color="BGRA")
    frames = list(iter_camera_frames(read_recording_info(write_recording(tmp_path / "d.mkv",
                                                                         spec))))
    for k, frame in enumerate(frames):
        assert frame.color is not None
        expected = cv2.cvtColor(color_image_bgr(1280, 720, k), cv2.COLOR_BGR2RGB)
        assert np.array_equal(frame.color.rgb(), expected)  # BGRA is lossless


def test_nv12_colour_is_read_as_rgb(tmp_path: Path) -> None:
    spec = RecordingSpec(**SMALL, color="NV12")
    info = read_recording_info(write_recording(tmp_path / "nv12.mkv", spec))
    assert info.color_format == "NV12"
    for k, frame in enumerate(iter_camera_frames(info)):
        assert frame.color is not None
        expected = cv2.cvtColor(color_image_bgr(1280, 720, k), cv2.COLOR_BGR2RGB)
        assert np.abs(frame.color.rgb().astype(int) - expected).mean() < 3  # chroma at 1/4


def test_a_recording_without_colour_gives_depth_alone(tmp_path: Path) -> None:
    info = read_recording_info(write_recording(tmp_path / "n.mkv",
                                               RecordingSpec(**SMALL, color=None)))
    assert info.color_format is None and info.color_size_px is None
    assert all(f.color is None for f in iter_camera_frames(info))


def test_refuses_a_file_that_is_not_matroska(tmp_path: Path) -> None:
    text = tmp_path / "notes.mkv"
    text.write_text("not a recording\n" * 100)
    _one_line_error(text, lambda: read_recording_info(text))
    png = tmp_path / "image.mkv"
    png.write_bytes(cv2.imencode(".png", np.zeros((8, 8), np.uint8))[1].tobytes())
    assert "Matroska" in _one_line_error(png, lambda: read_recording_info(png))


def test_refuses_a_recording_without_its_calibration(tmp_path: Path) -> None:
    path = write_recording(tmp_path / "nocal.mkv", RecordingSpec(**SMALL, calibration=None))
    assert "calibration" in _one_line_error(path, lambda: read_recording_info(path))


def test_refuses_a_calibration_that_is_not_one(tmp_path: Path) -> None:
    bad = json.dumps({"CalibrationInformation": {"Cameras": []}}).encode()
    path = write_recording(tmp_path / "badcal.mkv", RecordingSpec(**SMALL, calibration=bad))
    assert "depth camera" in _one_line_error(path, lambda: read_recording_info(path))


def test_refuses_a_truncated_recording_when_its_frames_end_early(tmp_path: Path) -> None:
    path = write_recording(tmp_path / "cut.mkv",
                           RecordingSpec(depth_mode="NFOV_2X2BINNED", frame_count=12))
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    info = read_recording_info(path)  # the header survives
    message = _one_line_error(path, lambda: list(iter_camera_frames(info)))
    assert "truncated" in message


def test_refuses_a_recording_cut_inside_its_header(tmp_path: Path) -> None:
    path = write_recording(tmp_path / "head.mkv", RecordingSpec(**SMALL))
    path.write_bytes(path.read_bytes()[:1000])
    _one_line_error(path, lambda: read_recording_info(path))


def test_refuses_a_passive_ir_recording_it_has_no_depth(tmp_path: Path) -> None:
    path = write_recording(tmp_path / "ir.mkv", RecordingSpec(depth_mode="PASSIVE_IR",
                                                              frame_count=2, color=None))
    assert "no depth track" in _one_line_error(path, lambda: read_recording_info(path))


def test_refuses_a_depth_track_that_is_not_b16g(tmp_path: Path) -> None:
    path = tmp_path / "rgb.mkv"
    out = av.open(str(path), "w", format="matroska")
    stream = out.add_stream("mjpeg", rate=30)
    stream.width, stream.height, stream.pix_fmt = 320, 288, "yuvj420p"
    stream.metadata["title"] = "DEPTH"
    stream.metadata["K4A_DEPTH_MODE"] = "NFOV_2X2BINNED"
    out.add_attachment("calibration.json", "application/octet-stream", calibration_json())
    frame = av.VideoFrame.from_ndarray(np.zeros((288, 320, 3), np.uint8), format="rgb24")
    for packet in [*stream.encode(frame.reformat(format="yuvj420p")), *stream.encode()]:
        out.mux(packet)
    out.close()
    assert "b16g" in _one_line_error(path, lambda: read_recording_info(path))
