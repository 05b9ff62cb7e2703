"""`volumesh reconstruct`: a small synthetic capture in, a mesh and a report out; bad input
gets one line and exit code 2."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pipeline.io.capture_io import write_capture
from pipeline.io.gltf_read import decode_glb
from pipeline.io.mesh_io import read_mesh, write_ply
from pipeline.synth.rig import RigConfig
from pipeline.synth.scene import SynthConfig, sample_mesh, synthesize, true_cameras

ROOT = Path(__file__).resolve().parents[2]


def _run_cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-c", "from app.cli import main; main()", *args],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Four cameras at 240x216 of the built-in subject, with a little pose error."""
    config = SynthConfig(camera_count=4, seed=3, rig=RigConfig(width=240, height=216),
                         pose_error_rot_deg=0.3, pose_error_trans_m=0.003)
    meta, views, truth = synthesize(sample_mesh(), config)
    out = tmp_path_factory.mktemp("cli") / "capture"
    write_capture(out, meta, views)
    write_ply(out.parent / "truth.ply", truth)
    poses = {c.id: np.asarray(c.world_from_depth).tolist()
             for c in true_cameras(truth, config)}
    (out.parent / "rig.json").write_text(json.dumps({"world_from_depth": poses}))
    return out


def test_reconstruct_writes_a_glb_and_a_report(capture: Path, tmp_path: Path) -> None:
    out, report = tmp_path / "out" / "mesh.glb", tmp_path / "report.json"
    result = _run_cli("reconstruct", str(capture), "--out", str(out), "--report", str(report),
                      "--ground-truth", str(capture.parent / "truth.ply"), "--no-enhance",
                      "--rig", str(capture.parent / "rig.json"), "--edge-length-mm", "20",
                      "--frame", "0")
    assert result.returncode == 0, result.stderr
    assert "wrote" in result.stdout and "C2M RMS" in result.stdout
    mesh = decode_glb(out.read_bytes())
    assert mesh.face_count > 1000 and mesh.vertex_colors is not None
    figures = json.loads(report.read_text())
    assert list(figures["stage_seconds"]) == figures["stages"]
    assert figures["triangles"] == mesh.face_count
    assert figures["output"]["bytes"] == out.stat().st_size
    assert figures["enhance"]["applied"] is False
    accuracy = figures["accuracy"]
    assert accuracy["result_to_gt"]["rms_m"] < 0.004
    assert accuracy["coverage_visible"] > 0.9
    for key in ("mean_m", "std_m", "rms_m", "p95_m"):
        assert key in accuracy["result_to_gt"] and key in accuracy["gt_to_result"]


def test_reconstruct_enhances_when_asked(capture: Path, tmp_path: Path) -> None:
    out, report = tmp_path / "mesh.ply", tmp_path / "report.json"
    result = _run_cli("reconstruct", str(capture), "--out", str(out), "--report", str(report),
                      "--edge-length-mm", "30", "--enhance")
    assert result.returncode == 0, result.stderr
    figures = json.loads(report.read_text())
    assert figures["enhance"] == {"requested": True, "applied": True}
    remeshed = figures["stages"].index("remesh")
    assert figures["stages"][remeshed:remeshed + 3] == ["remesh", "fit", "enhance"]
    moved = figures["stage_stats"]["enhance"]
    # The synthetic capture reconstructs to a clean surface: the networks leave it as it is.
    assert moved["method"] == "regressor" and moved["noise_ratio"] < 0.05
    assert moved["skipped_as_clean"] is True and moved["max_offset_m"] < 1e-6
    assert read_mesh(out).face_count == figures["triangles"]


def test_reconstruct_writes_ply(capture: Path, tmp_path: Path) -> None:
    out = tmp_path / "mesh.ply"
    result = _run_cli("reconstruct", str(capture), "--out", str(out), "--edge-length-mm", "30")
    assert result.returncode == 0, result.stderr
    assert read_mesh(out).face_count > 500


@pytest.mark.parametrize("args, fragment", [
    (["reconstruct", "/nonexistent/capture", "--out", "x.glb"], "/nonexistent/capture"),
    (["reconstruct", "{capture}", "--out", "mesh.obj"], "--out"),
    (["reconstruct", "{capture}", "--out", "x.glb", "--frame", "9"], "frame"),
    (["reconstruct", "{capture}", "--out", "x.glb", "--edge-length-mm", "-1"],
     "--edge-length-mm"),
    (["reconstruct", "{capture}", "--out", "x.glb", "--rig", "{bad_rig}"], "world_from_depth"),
    (["reconstruct", "{capture}", "--out", "x.glb", "--rig", "{not_json}"], "--rig"),
])
def test_bad_input_is_one_line_and_exit_2(capture: Path, tmp_path: Path, args: list[str],
                                          fragment: str) -> None:
    bad_rig = tmp_path / "bad_rig.json"
    bad_rig.write_text(json.dumps({"world_from_depth": {"cam0": [[1, 2], [3, 4]]}}))
    not_json = tmp_path / "rig.json"
    not_json.write_text("{nope")
    filled = [a.format(capture=capture, bad_rig=bad_rig, not_json=not_json) for a in args]
    filled = [str(tmp_path / a) if a == "x.glb" else a for a in filled]
    result = _run_cli(*filled)
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("volumesh: error: "), result.stderr
    assert fragment in lines[0]
    assert not (tmp_path / "x.glb").exists()
