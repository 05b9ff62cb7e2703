"""`volumesh synth --target` then `volumesh calibrate`: a rig.json close to the true rig;
bad input ends with one line and exit code 2."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from app.cli import app
from pipeline.calibration.evaluate import pose_errors
from pipeline.capture import CameraInfo, CaptureMeta, FrameInfo, Intrinsics, View
from pipeline.io.capture_io import write_capture
from pipeline.io.rig_io import read_rig

ROOT = Path(__file__).resolve().parents[3]


def test_synth_target_then_calibrate(tmp_path: Path) -> None:
    capture = tmp_path / "calib"
    runner = CliRunner()
    made = runner.invoke(app, ["synth", "--target", "cube", "--cameras", "4", "--frames", "5",
                               "--out", str(capture), "--seed", "2"])
    assert made.exit_code == 0, made.output
    assert (capture / "true_rig.json").is_file()
    done = runner.invoke(app, ["calibrate", str(capture), "--out", str(tmp_path / "rig.json")])
    assert done.exit_code == 0, done.output
    assert "wrote" in done.output and "reprojection RMS" in done.output
    poses, report = read_rig(tmp_path / "rig.json")
    truth, _ = read_rig(capture / "true_rig.json")
    errors = pose_errors(poses, truth)
    assert errors["rotation_deg_max"] < 0.1 and errors["translation_mm_max"] < 3.0
    assert set(report["views_used"]) == {"cam0", "cam1", "cam2", "cam3"}
    doc = json.loads((tmp_path / "rig.json").read_text())
    assert doc["format"] == "volumesh.rig/1" and "triangulation_error_mm" in doc


def test_calibrate_without_target_exits_2_with_one_line(tmp_path: Path) -> None:
    intrinsics = Intrinsics(64, 48, 50.0, 50.0, 31.5, 23.5)
    camera = CameraInfo("cam0", intrinsics)
    meta = CaptureMeta(0.001, (camera,), (FrameInfo(0, 0),))
    write_capture(tmp_path / "cap", meta, [View(camera, 0, np.ones((48, 64), np.float32))])
    result = subprocess.run([sys.executable, "-c", "from app.cli import main; main()",
                             "calibrate", str(tmp_path / "cap"), "--out",
                             str(tmp_path / "rig.json")],
                            cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert result.returncode == 2
    assert result.stderr.strip().splitlines()[-1].startswith("volumesh: error: capture.json: "
                                                             "target is null")
    assert not (tmp_path / "rig.json").exists()
