"""rig.json: poses and report round-trip; broken files are refused naming the field."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from pipeline.calibration.transforms import from_rotvec
from pipeline.io.rig_io import RIG_FORMAT_ID, read_rig, rig_from_json, rig_to_json, write_rig


@settings(max_examples=25)
@given(arrays(np.float64, (3, 3), elements=st.floats(-3, 3)))
def test_poses_round_trip_exactly(values: np.ndarray) -> None:
    poses = {f"cam{i}": from_rotvec(values[i] / 3, values[i]) for i in range(3)}
    back, report = rig_from_json(json.loads(json.dumps(rig_to_json(poses, {"note": 1}))))
    assert report == {"note": 1}
    for camera_id, pose in poses.items():
        np.testing.assert_array_equal(back[camera_id], pose)


def test_write_and_read_with_a_report(tmp_path: Path) -> None:
    report = {"reprojection_rms_px": {"a": np.float64(0.1), "b": float("nan")},
              "views_used": {"a": np.int64(5)}, "warnings": ["w"], "history": np.array([1.0])}
    write_rig(tmp_path / "rig.json", {"a": np.eye(4), "b": np.eye(4)}, report)
    doc = json.loads((tmp_path / "rig.json").read_text())
    assert doc["format"] == RIG_FORMAT_ID
    assert doc["reprojection_rms_px"] == {"a": 0.1, "b": None}
    poses, back = read_rig(tmp_path / "rig.json")
    assert sorted(poses) == ["a", "b"] and back["views_used"] == {"a": 5}


@pytest.mark.parametrize("document,message", [
    ([], "must be a JSON object"),
    ({"format": "other/2", "world_from_depth": {"a": np.eye(4).tolist()}}, "unknown format"),
    ({"world_from_depth": {}}, "world_from_depth: must be a non-empty object"),
    ({"world_from_depth": {"bad id!": np.eye(4).tolist()}}, "camera id 'bad id!'"),
    ({"world_from_depth": {"a": [[1, 0, 0], [0, 1, 0]]}}, r"world_from_depth\.a: must be a 4x4"),
    ({"world_from_depth": {"a": (2 * np.eye(4)).tolist()}}, r"world_from_depth\.a: last row"),
    ({"world_from_depth": {"a": np.diag([2.0, 1, 1, 1]).tolist()}}, "is not rigid"),
    ({"world_from_depth": {"a": [["x"] * 4] * 4}}, "4x4 nested list of numbers"),
])
def test_broken_rig_files_are_refused(document: object, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        rig_from_json(document)


def test_unreadable_rig_file(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="cannot read rig file"):
        read_rig(tmp_path / "missing.json")
    (tmp_path / "bad.json").write_text("{nope")
    with pytest.raises(ValueError, match="bad.json: not valid JSON"):
        read_rig(tmp_path / "bad.json")
