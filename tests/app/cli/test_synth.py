"""`volumesh synth`: writes a capture the reader accepts, ground truth beside it."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from app.cli import app
from pipeline.io.capture_io import open_capture
from pipeline.io.mesh_io import read_mesh
from pipeline.synth.rig import rig_cameras
from pipeline.synth.scene import SynthConfig

ROOT = Path(__file__).resolve().parents[3]


def _run_cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-c", "from app.cli import main; main()", *args],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)


def test_synth_writes_a_readable_capture_with_pose_error(tmp_path: Path) -> None:
    out = tmp_path / "cap"
    result = CliRunner().invoke(app, [
        "synth", "--mesh", "sample", "--out", str(out), "--cameras", "2", "--frames", "2",
        "--pose-error-deg", "1.5", "--pose-error-mm", "5", "--seed", "4", "--zip"])
    assert result.exit_code == 0, result.output
    truth = read_mesh(out / "ground_truth.ply")
    assert truth.vertices_m[:, 1].min() == pytest.approx(0.0, abs=1e-6)
    assert truth.vertices_m[:, 1].max() == pytest.approx(1.8, abs=1e-6)
    true_doc = json.loads((out / "true_rig.json").read_text())
    true_poses = rig_cameras(SynthConfig(camera_count=2).rig_config())
    for cam in true_poses:
        assert cam.world_from_depth is not None
        np.testing.assert_allclose(true_doc["world_from_depth"][cam.id], cam.world_from_depth)
    for path in (out, tmp_path / "cap.zip"):
        with open_capture(path) as capture:
            assert capture.meta.camera_ids == ("cam0", "cam1")
            assert capture.meta.frame_indices == (0, 1)
            for cam, true_cam in zip(capture.meta.cameras, true_poses, strict=True):
                written, true = cam.world_from_depth, true_cam.world_from_depth
                assert written is not None and true is not None
                moved_mm = 1000 * np.linalg.norm(written[:3, 3] - true[:3, 3])
                assert moved_mm == pytest.approx(5.0, abs=1e-3)
                cos = (np.trace(true[:3, :3].T @ written[:3, :3]) - 1) / 2
                assert math.degrees(math.acos(cos)) == pytest.approx(1.5, abs=1e-4)
            view = capture.read_view("cam1", 1)
            assert view.depth_m.shape == (576, 640)
            valid = view.depth_m[view.depth_m > 0]
            assert valid.size > 10_000 and valid.min() >= 0.5 and valid.max() <= 3.86
            assert view.color_rgb is not None and view.color_rgb.shape == (576, 640, 3)
    with open_capture(tmp_path / "cap.zip") as capture:
        assert capture.meta.camera_ids == ("cam0", "cam1")


def test_synth_of_an_obj_without_noise(tmp_path: Path) -> None:
    mesh = tmp_path / "box.obj"
    corners = [(x, y, z) for x in (0, 1) for y in (0, 1) for z in (0, 2)]
    faces = [(1, 2, 4), (1, 4, 3), (5, 7, 8), (5, 8, 6), (1, 5, 6), (1, 6, 2),
             (3, 4, 8), (3, 8, 7), (1, 3, 7), (1, 7, 5), (2, 6, 8), (2, 8, 4)]
    mesh.write_text("".join(f"v {x} {y} {z}\n" for x, y, z in corners)
                    + "".join(f"f {a} {b} {c}\n" for a, b, c in faces))
    out = tmp_path / "box"
    result = CliRunner().invoke(app, ["synth", "--mesh", str(mesh), "--out", str(out),
                                      "--cameras", "1", "--up-axis", "+z", "--height-m", "1.0",
                                      "--no-noise"])
    assert result.exit_code == 0, result.output
    truth = read_mesh(out / "ground_truth.ply")
    extent = truth.vertices_m.max(axis=0) - truth.vertices_m.min(axis=0)
    np.testing.assert_allclose(extent, [0.5, 1.0, 0.5], atol=1e-6)
    with open_capture(out) as capture:
        depth = capture.read_view("cam0", 0).depth_m
    # Camera 0 stands at azimuth 0, 2 m out, 2 m up, seeing the box's +Z face and top.
    assert 1.5 < depth[depth > 0].min() < depth[depth > 0].max() < 2.6


def test_synth_errors_are_one_line_and_exit_2(tmp_path: Path) -> None:
    missing = _run_cli("synth", "--mesh", str(tmp_path / "none.obj"), "--out",
                       str(tmp_path / "x"))
    assert missing.returncode == 2
    assert missing.stderr.strip().startswith("volumesh: error:") and "none.obj" in missing.stderr
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "keep.txt").write_text("mine")
    runner = CliRunner()
    busy = runner.invoke(app, ["synth", "--mesh", "sample", "--out", str(tmp_path / "busy")])
    assert isinstance(busy.exception, ValueError) and "--overwrite" in str(busy.exception)
    forced = runner.invoke(app, ["synth", "--mesh", "sample", "--out", str(tmp_path / "busy"),
                                 "--overwrite"])
    assert isinstance(forced.exception, ValueError) and "capture.json" in str(forced.exception)
    assert (tmp_path / "busy" / "keep.txt").read_text() == "mine"


def test_overwrite_replaces_a_previous_capture(tmp_path: Path) -> None:
    out = tmp_path / "cap"
    runner = CliRunner()
    first = runner.invoke(app, ["synth", "--mesh", "sample", "--out", str(out),
                                "--cameras", "3", "--no-noise"])
    assert first.exit_code == 0, first.output
    second = runner.invoke(app, ["synth", "--mesh", "sample", "--out", str(out),
                                 "--cameras", "1", "--no-noise", "--overwrite"])
    assert second.exit_code == 0, second.output
    assert not (out / "cam2").exists()
    with open_capture(out) as capture:
        assert capture.meta.camera_ids == ("cam0",)


def test_synth_writes_a_moving_sequence_with_its_truth(tmp_path: Path) -> None:
    out = tmp_path / "moving"
    result = CliRunner().invoke(app, [
        "synth", "--mesh", "sample", "--out", str(out), "--cameras", "2", "--frames", "3",
        "--motion", "rigid", "--fps", "10"])
    assert result.exit_code == 0, result.output
    assert "3 frame(s) at 10 fps, rigid subject" in result.output
    truth = json.loads((out / "truth_poses.json").read_text())
    poses = np.array(truth["world_from_subject"])
    assert truth["fps"] == 10 and poses.shape == (3, 4, 4)
    np.testing.assert_allclose(poses[0], np.eye(4), atol=1e-12)
    assert not np.allclose(poses[1], poses[2])
    with open_capture(out) as capture:
        assert [f.timestamp_us for f in capture.meta.frames] == [0, 100_000, 200_000]
        first, last = capture.read_view("cam0", 0), capture.read_view("cam0", 2)
        assert not np.array_equal(first.depth_m > 0, last.depth_m > 0)  # the subject moved
    refused = CliRunner().invoke(app, ["synth", "--mesh", "sample", "--out",
                                       str(tmp_path / "x"), "--motion", "dance"])
    assert refused.exit_code != 0 and "--motion" in str(refused.output) + str(refused.exception)
