"""End to end: a calibration capture on disk in, camera poses and a report out; broken
captures end with a message naming the problem."""

from __future__ import annotations

import dataclasses
import json
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from pipeline.calibration import CalibrationConfig, calibrate
from pipeline.calibration.calibrate import WORLD_FROM_REFERENCE
from pipeline.calibration.evaluate import pose_errors
from pipeline.io.capture_io import open_capture, write_capture
from tests.pipeline.calibration.conftest import SmallCapture


def test_calibrates_a_small_synthetic_rig(small_capture: SmallCapture) -> None:
    fractions: list[float] = []
    with open_capture(small_capture.path) as reader:
        world_from_depth, report = calibrate(reader, CalibrationConfig(), fractions.append)
    assert sorted(world_from_depth) == sorted(small_capture.truth)
    errors = pose_errors(world_from_depth, small_capture.truth)
    assert errors["rotation_deg_max"] < 0.1
    assert errors["translation_mm_max"] < 3.0
    # The world is the first camera's depth frame turned to +Y up.
    np.testing.assert_allclose(world_from_depth["cam0"], WORLD_FROM_REFERENCE, atol=1e-12)
    assert fractions == sorted(fractions) and fractions[-1] == 1.0
    assert all(0 < v < 0.5 for v in report["reprojection_rms_px"].values())
    assert report["triangulation_error_mm"]["median"] < 1.0
    assert all(n >= 2 for n in report["views_used"].values())
    json.dumps(report)  # the report goes into rig.json as it is


def _copy(small: SmallCapture, out: Path, blank: tuple[str, ...] = ()) -> Path:
    """A copy of the capture; the colour images of the ``blank`` cameras show a grey wall."""
    shutil.copytree(small.path, out)
    for camera_id in blank:
        for image in (out / camera_id / "color").iterdir():
            shape = np.asarray(cv2.imread(str(image))).shape
            cv2.imwrite(str(image), np.full(shape, 90, np.uint8))
    return out


def _edit_json(path: Path, edit: Callable[[dict[str, Any]], None]) -> None:
    doc = json.loads((path / "capture.json").read_text())
    edit(doc)
    (path / "capture.json").write_text(json.dumps(doc))


def test_capture_without_target_description(small_capture: SmallCapture, tmp_path: Path) -> None:
    path = _copy(small_capture, tmp_path / "cap")
    _edit_json(path, lambda doc: doc.update(target=None))
    with open_capture(path) as reader, pytest.raises(ValueError, match="target is null"):
        calibrate(reader)


def test_target_nowhere_in_the_images(small_capture: SmallCapture, tmp_path: Path) -> None:
    path = _copy(small_capture, tmp_path / "cap", blank=("cam0", "cam1", "cam2", "cam3"))
    with open_capture(path) as reader, pytest.raises(ValueError, match="no ChArUco corners"):
        calibrate(reader)


def test_board_seen_by_one_camera_only(small_capture: SmallCapture, tmp_path: Path) -> None:
    path = _copy(small_capture, tmp_path / "cap", blank=("cam1", "cam2", "cam3"))
    with open_capture(path) as reader, pytest.raises(
            ValueError, match=r"camera\(s\) cam1, cam2, cam3 saw no usable view"):
        calibrate(reader)


def test_unknown_dictionary_is_refused_when_opening(small_capture: SmallCapture,
                                                    tmp_path: Path) -> None:
    path = _copy(small_capture, tmp_path / "cap")
    _edit_json(path, lambda doc: doc["target"]["boards"][0].update(dictionary="DICT_5X5_7"))
    with pytest.raises(ValueError, match="unknown ArUco dictionary 'DICT_5X5_7'"):
        open_capture(path)


def test_corrupt_colour_image_is_named(small_capture: SmallCapture, tmp_path: Path) -> None:
    path = _copy(small_capture, tmp_path / "cap")
    image = path / "cam2" / "color" / "000003.png"
    data = bytearray(image.read_bytes())
    data[100:] = bytes(len(data) - 100)  # header intact, pixel data destroyed
    image.write_bytes(bytes(data))
    with open_capture(path) as reader, pytest.raises(
            ValueError, match=r"cam2/color/000003\.png: image data are corrupt"):
        calibrate(reader)


def test_colourless_capture_is_refused(small_capture: SmallCapture, tmp_path: Path) -> None:
    views = [dataclasses.replace(v, color_rgb=None) for v in small_capture.views]
    write_capture(tmp_path / "cap", small_capture.meta, views)
    with open_capture(tmp_path / "cap") as reader, pytest.raises(
            ValueError, match="have no colour images"):
        calibrate(reader)


def test_unknown_reference_camera(small_capture: SmallCapture) -> None:
    with open_capture(small_capture.path) as reader, pytest.raises(
            ValueError, match="reference_camera: capture has no camera 'nope'"):
        calibrate(reader, CalibrationConfig(reference_camera="nope"))


def test_registered_colour_without_colour_model(tmp_path: Path) -> None:
    """Other tools may register colour to depth (no color_intrinsics, no color_from_depth)."""
    from pipeline.synth.rig import RigConfig, rig_cameras
    from pipeline.synth.target import synthesize_calibration
    from tests.pipeline.calibration.conftest import small_config

    rig = rig_cameras(RigConfig(camera_count=4, radius_m=1.5, width=800, height=450,
                                fov_x_deg=80.0, fov_y_deg=48.0, upper_height_m=1.6,
                                lower_height_m=0.9))
    same = [dataclasses.replace(c, color_intrinsics=c.depth_intrinsics,
                                color_from_depth=np.eye(4)) for c in rig]
    meta, views, truth = synthesize_calibration(small_config(depth_noise=False, frame_count=6),
                                                cameras=same)
    registered = tuple(dataclasses.replace(c, color_intrinsics=None, color_from_depth=None)
                       for c in meta.cameras)
    by_id = {c.id: c for c in registered}
    write_capture(tmp_path / "cap", dataclasses.replace(meta, cameras=registered),
                  [dataclasses.replace(v, camera=by_id[v.camera.id]) for v in views])
    with open_capture(tmp_path / "cap") as reader:
        world_from_depth, _ = calibrate(reader)
    errors = pose_errors(world_from_depth, truth)
    assert errors["rotation_deg_max"] < 0.1 and errors["translation_mm_max"] < 3.0
