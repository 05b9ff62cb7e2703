"""`volumesh agent` refuses bad input in one line with exit code 2, before it touches a
gateway."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
UNREACHABLE = "http://127.0.0.1:9"


def _agent(*args: str, env: dict[str, str] | None = None, cwd: Path = ROOT
           ) -> subprocess.CompletedProcess[str]:
    base = {k: v for k, v in os.environ.items() if k != "VOLUMESH_API_KEY"}
    base["PYTHONPATH"] = os.pathsep.join(filter(None, [(env or {}).pop("PYTHONPATH", None),
                                                       str(ROOT)]))
    return subprocess.run([sys.executable, "-c", "from app.cli import main; main()", "agent",
                           *args], cwd=cwd, env={**base, **(env or {})}, capture_output=True,
                          text=True, timeout=120)


def _one_line(result: subprocess.CompletedProcess[str]) -> str:
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    return lines[0]


def test_an_unknown_source_names_the_kinds(tmp_path: Path) -> None:
    line = _one_line(_agent("--gateway", UNREACHABLE, "--key", "k", "--source", "webcam",
                            cwd=tmp_path))
    assert "unknown source 'webcam'" in line and "capture:DIR" in line and "k4a" in line
    assert not (tmp_path / "volumesh-spool").exists()  # nothing made for bad input


def test_a_missing_key_says_where_a_key_comes_from() -> None:
    line = _one_line(_agent("--gateway", UNREACHABLE, "--source", "synthetic"))
    assert "--key" in line and "VOLUMESH_API_KEY" in line


def test_the_key_may_come_from_the_environment(tmp_path: Path) -> None:
    line = _one_line(_agent("--gateway", UNREACHABLE, "--source", f"capture:{tmp_path}/none",
                            env={"VOLUMESH_API_KEY": "k"}))
    assert "no such capture" in line  # past the key


def test_a_bad_url_and_missing_files_are_named() -> None:
    assert "--gateway" in _one_line(_agent("--gateway", "localhost:8000", "--key", "k",
                                           "--source", "synthetic"))
    assert "missing.mkv: no such recording" in _one_line(
        _agent("--gateway", UNREACHABLE, "--key", "k", "--source", "mkv:missing.mkv"))


def test_the_k4a_source_without_pyk4a_says_how_to_install_it(tmp_path: Path) -> None:
    # pyk4a is not a dependency; a module that fails to import stands for it not installed,
    # whatever this environment has.
    (tmp_path / "pyk4a.py").write_text("raise ImportError('pyk4a is not installed')\n")
    line = _one_line(_agent("--gateway", UNREACHABLE, "--key", "k", "--source", "k4a",
                            env={"PYTHONPATH": str(tmp_path)}))
    assert line.endswith("the k4a source needs pyk4a: pip install 'volumesh[k4a]'")


def test_a_spool_of_another_source_is_refused_with_how_to_finish_or_clear_it(
        tmp_path: Path) -> None:
    spool = tmp_path / "spool"
    (spool / "frames").mkdir(parents=True)
    (spool / "state.json").write_text(json.dumps({
        "gateway_url": UNREACHABLE, "stream_id": "st1", "source": "capture:elsewhere",
        "depth_scale": 0.001, "cameras": [], "next_index": 3, "next_position": 3,
        "source_done": False}))
    line = _one_line(_agent("--gateway", UNREACHABLE, "--key", "k", "--source", "synthetic",
                            "--frames", "1", "--spool", str(spool)))
    assert "holds stream st1 of --source capture:elsewhere" in line
    assert "finish it by running again with that --source and --gateway" in line
    assert "delete the folder" in line
