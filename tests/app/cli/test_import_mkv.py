"""`volumesh import-mkv`: Azure Kinect recordings of a rig to a capture the reader accepts."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

from pipeline.calibration.evaluate import pose_errors
from pipeline.io.capture_io import open_capture
from pipeline.io.capture_json import meta_to_json
from pipeline.synth.target import TargetSynthConfig, synthesize_calibration
from tests.k4a_recordings import (
    COLOR_PARAMS,
    COLOR_ROTATION,
    COLOR_TRANSLATION_M,
    DEPTH_PARAMS,
    RecordingSpec,
    calibration_json_of,
    color_image_bgr,
    depth_image_mm,
    write_recording,
)

ROOT = Path(__file__).resolve().parents[3]
MASTER, SUB = "000000000010", "000000000020"
START_NS = 1_000_000_000
SUB_DELAY_NS = 20_000_000  # more than half a frame: matching must take the delay off


def _run(*args: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "app", "import-mkv", *map(str, args)],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)


def _rig(folder: Path) -> tuple[Path, Path]:
    """A master with colour (frames 0-7) and a subordinate without, 20 ms behind the master's
    trigger, recording from two frames earlier and losing the depth of its frame 5."""
    master = write_recording(folder / "master.mkv", RecordingSpec(
        depth_mode="NFOV_2X2BINNED", frame_count=8, sync_mode="MASTER", serial=MASTER,
        start_offset_ns=START_NS))
    sub = write_recording(folder / "sub.mkv", RecordingSpec(
        depth_mode="NFOV_2X2BINNED", frame_count=10, sync_mode="SUBORDINATE", color=None,
        subordinate_delay_ns=SUB_DELAY_NS, serial=SUB, seed=1, dropped_depth=frozenset({5}),
        start_offset_ns=START_NS - 66_000_000 + SUB_DELAY_NS))
    return master, sub


def test_imports_a_synced_rig_matching_frames_by_device_timestamp(tmp_path: Path) -> None:
    master, sub = _rig(tmp_path)
    out = tmp_path / "take.zip"
    result = _run(master, sub, "--out", out)
    assert result.returncode == 0, result.stderr
    assert "skipped 1 incomplete frame-set(s), frames missing from: 000000000020 1" in \
        result.stdout
    assert "2 frame-set(s) outside" in result.stdout
    # master frames 0-7 but 3, where the subordinate (its frame 5) lost its depth
    master_frames = [0, 1, 2, 4, 5, 6, 7]
    with open_capture(out) as capture:
        meta = capture.meta
        assert meta.camera_ids == (MASTER, SUB)
        assert meta.frame_indices == tuple(range(len(master_frames)))
        assert all(c.world_from_depth is None for c in meta.cameras)
        for index, k in enumerate(master_frames):
            sub_k = k + 2  # the subordinate's own frame number at master frame k
            master_us = START_NS // 1000 + (k * 1000 // 30) * 1000
            sub_us = (START_NS - 66_000_000) // 1000 + (sub_k * 1000 // 30) * 1000
            assert meta.frames[index].timestamp_us == min(master_us, sub_us)
            master_view, sub_view = capture.read_frame(index)
            assert np.array_equal(np.rint(master_view.depth_m * 1000).astype(np.uint16),
                                  depth_image_mm(320, 288, k))
            assert np.array_equal(np.rint(sub_view.depth_m * 1000).astype(np.uint16),
                                  depth_image_mm(320, 288, sub_k, seed=1))
            expected = cv2.cvtColor(color_image_bgr(1280, 720, k), cv2.COLOR_BGR2RGB)
            assert master_view.color_rgb is not None and sub_view.color_rgb is None
            assert np.abs(master_view.color_rgb.astype(int) - expected).mean() < 3


def test_the_capture_carries_each_modes_intrinsics_and_colour_from_depth(
        tmp_path: Path) -> None:
    master, sub = _rig(tmp_path)
    out = tmp_path / "take"
    assert _run(master, sub, "--out", out).returncode == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["master.mkv", "sub.mkv", "take"]
    with open_capture(out) as capture:
        cam, sub_cam = capture.meta.cameras
    cx, cy, fx, fy = DEPTH_PARAMS[:4]
    depth = cam.depth_intrinsics  # NFOV 2x2 binned: the 512x512 sensor less (96, 90)
    assert (depth.width, depth.height) == (320, 288)
    assert (depth.fx, depth.fy) == pytest.approx((fx * 512, fy * 512))
    assert (depth.cx, depth.cy) == pytest.approx((cx * 512 - 96.5, cy * 512 - 90.5))
    assert sub_cam.depth_intrinsics == depth and sub_cam.color_intrinsics is None
    ccx, ccy, cfx, cfy = COLOR_PARAMS[:4]
    color = cam.color_intrinsics  # 720p: the 1280x960 sensor less 120 rows at the top
    assert color is not None and (color.width, color.height) == (1280, 720)
    assert (color.fx, color.fy) == pytest.approx((cfx * 1280, cfy * 960))
    assert (color.cx, color.cy) == pytest.approx((ccx * 1280 - 0.5, ccy * 960 - 120.5))
    expected = np.eye(4)
    expected[:3, :3] = np.reshape(COLOR_ROTATION, (3, 3))
    expected[:3, 3] = COLOR_TRANSLATION_M
    assert cam.color_from_depth == pytest.approx(expected)


def test_the_sync_window_is_a_setting(tmp_path: Path) -> None:
    master, sub = _rig(tmp_path)
    # the writer's millisecond blocks put some frames of one instant 1 ms apart
    wide = _run(master, sub, "--out", tmp_path / "wide")
    narrow = _run(master, sub, "--out", tmp_path / "narrow", "--sync-window-us", "500")
    assert wide.returncode == 0 and narrow.returncode == 0, narrow.stderr
    with open_capture(tmp_path / "wide") as a, open_capture(tmp_path / "narrow") as b:
        assert 0 < len(b.meta.frames) < len(a.meta.frames)


def _refused(result: subprocess.CompletedProcess[str], name: str) -> str:
    assert result.returncode == 2, result.stdout + result.stderr
    assert "Traceback" not in result.stderr
    last = result.stderr.strip().splitlines()[-1]
    assert last.startswith("volumesh: error: ") and name in last, result.stderr
    return last


def _truncated(folder: Path) -> Path:
    path = write_recording(folder / "cut.mkv", RecordingSpec(depth_mode="NFOV_2X2BINNED",
                                                             frame_count=12, serial="7"))
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    return path


def _no_calibration(folder: Path) -> Path:
    return write_recording(folder / "nocal.mkv", RecordingSpec(
        depth_mode="NFOV_2X2BINNED", frame_count=3, serial="7", calibration=None))


def _other_depth_mode(folder: Path) -> Path:
    return write_recording(folder / "wide.mkv", RecordingSpec(
        depth_mode="WFOV_2X2BINNED", frame_count=3, serial="7"))


def _not_matroska(folder: Path) -> Path:
    path = folder / "notes.mkv"
    path.write_text("not a recording\n")
    return path


@pytest.mark.parametrize(("make", "says"), [
    (_truncated, "truncated"), (_no_calibration, "no calibration attachment"),
    (_other_depth_mode, "depth mode WFOV_2X2BINNED differs"), (_not_matroska, "Matroska")])
def test_refuses_a_bad_recording_in_one_line_naming_it(tmp_path: Path, make: object,
                                                         says: str) -> None:
    master, _ = _rig(tmp_path)
    bad = make(tmp_path)  # type: ignore[operator]
    out = tmp_path / "take"
    last = _refused(_run(master, bad, "--out", out), bad.name)
    assert says in last
    assert not out.exists() and not any(p.name.startswith(".take") for p in tmp_path.iterdir())


def test_refuses_two_recordings_of_one_device_and_an_existing_out(tmp_path: Path) -> None:
    master, _ = _rig(tmp_path)
    assert "same device" in _refused(_run(master, master, "--out", tmp_path / "t"),
                                     master.name)
    (tmp_path / "t").mkdir()
    (tmp_path / "t" / "keep.txt").write_text("mine")
    assert "exists" in _refused(_run(master, "--out", tmp_path / "t"), "t")
    assert (tmp_path / "t" / "keep.txt").read_text() == "mine"


@pytest.mark.slow
def test_a_calibration_recording_imported_with_its_target_calibrates_the_rig(
        tmp_path: Path) -> None:
    config = TargetSynthConfig(kind="plane", frame_count=16, camera_count=4, seed=2)
    meta, views, truth = synthesize_calibration(config)
    depth_mm: dict[str, list[NDArray[np.uint16]]] = {c.id: [] for c in meta.cameras}
    jpegs: dict[str, list[bytes]] = {c.id: [] for c in meta.cameras}
    for view in views:  # frame by frame, camera by camera
        depth_mm[view.camera.id].append(np.rint(view.depth_m * 1000).astype(np.uint16))
        assert view.color_rgb is not None
        bgr = cv2.cvtColor(view.color_rgb, cv2.COLOR_RGB2BGR)
        jpegs[view.camera.id].append(cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 97])[1]
                                     .tobytes())
    recordings, serial_of = [], {}
    for number, camera in enumerate(meta.cameras):
        assert camera.color_intrinsics is not None and camera.color_from_depth is not None
        serial_of[camera.id] = f"{number + 1:012d}"
        spec = RecordingSpec(
            frame_count=config.frame_count, serial=serial_of[camera.id],
            sync_mode="MASTER" if number == 0 else "SUBORDINATE",
            subordinate_delay_ns=160_000 * number, start_offset_ns=START_NS + 160_000 * number,
            calibration=calibration_json_of(camera.depth_intrinsics, camera.color_intrinsics,
                                            camera.color_from_depth))
        recordings.append(write_recording(
            tmp_path / f"{camera.id}.mkv", spec, lambda k, c=camera.id: depth_mm[c][k],
            lambda k, c=camera.id: cv2.imdecode(np.frombuffer(jpegs[c][k], np.uint8),
                                                cv2.IMREAD_COLOR)))
    target = tmp_path / "board.json"
    target.write_text(json.dumps(meta_to_json(meta)["target"]))
    result = _run(*recordings, "--target", target, "--out", tmp_path / "calib.zip")
    assert result.returncode == 0, result.stderr
    with open_capture(tmp_path / "calib.zip") as capture:
        assert meta_to_json(capture.meta)["target"] == meta_to_json(meta)["target"]
        imported = {c.id: c for c in capture.meta.cameras}
        for camera in meta.cameras:  # the SDK's rules, run forwards, give the synthetic models
            back = imported[serial_of[camera.id]]
            assert back.depth_intrinsics.fx == pytest.approx(camera.depth_intrinsics.fx)
            assert back.depth_intrinsics.cy == pytest.approx(camera.depth_intrinsics.cy)
            assert back.color_intrinsics is not None and camera.color_intrinsics is not None
            assert back.color_intrinsics.cx == pytest.approx(camera.color_intrinsics.cx)
            assert back.color_intrinsics.distortion_coeffs() == pytest.approx(
                camera.color_intrinsics.distortion_coeffs())
    rig = tmp_path / "rig.json"
    calibrated = subprocess.run([sys.executable, "-m", "app", "calibrate",
                                 str(tmp_path / "calib.zip"), "--out", str(rig)],
                                cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert calibrated.returncode == 0, calibrated.stderr
    poses = {cam: np.array(m) for cam, m in json.loads(rig.read_text())["world_from_depth"]
             .items()}
    errors = pose_errors(poses, {serial_of[c]: pose for c, pose in truth.items()})
    assert errors["rotation_deg_max"] < 0.1 and errors["translation_mm_max"] < 2.0, errors
