"""`volumesh train --average`: a folder between two weights folders, or one clear line; the
command it replaces names it."""

import subprocess
import sys

import torch

from pipeline.enhance.models.regressor import RegressorConfig, ResidualUNet
from pipeline.enhance.weights.loading import load_regressor, regressor_to_bytes


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", "from app.cli import main; main()", *args],
                          capture_output=True, text=True, timeout=120)


def _weights_folder(path, seed: int):
    """A folder with the three depth networks' files (tiny regressors stand in for all three:
    the average reads them alike) and a vertex gain file."""
    torch.manual_seed(seed)
    path.mkdir()
    for name in ("regressor", "vae", "ldm"):
        (path / f"{name}.safetensors").write_bytes(
            regressor_to_bytes(ResidualUNet(RegressorConfig(channels=(4, 8)))))
    (path / "ldm_gain.safetensors").write_bytes(f"gain {seed}".encode())
    return path


def test_average_writes_the_networks_between_and_end_s_other_files(tmp_path):
    start, end = _weights_folder(tmp_path / "a", 1), _weights_folder(tmp_path / "b", 2)
    out = tmp_path / "mixed"
    done = _cli("train", "--average", str(start), str(end), "--out", str(out), "--share", "0.5")
    assert done.returncode == 0, done.stderr
    assert (out / "ldm_gain.safetensors").read_bytes() == b"gain 2"
    for name in ("regressor", "vae", "ldm"):
        a, b, m = (load_regressor((d / f"{name}.safetensors").read_bytes()).state_dict()
                   for d in (start, end, out))
        for k in m:
            assert torch.allclose(m[k], (a[k] + b[k]) / 2, atol=2e-3, rtol=0)


def test_average_names_what_is_wrong_and_writes_nothing(tmp_path):
    start, end = _weights_folder(tmp_path / "a", 1), _weights_folder(tmp_path / "b", 2)
    (end / "vae.safetensors").unlink()
    missing = _cli("train", "--average", str(start), str(end), "--out", str(tmp_path / "x"))
    assert missing.returncode == 2
    assert missing.stderr.strip().splitlines()[-1].endswith("has no vae.safetensors")
    (end / "vae.safetensors").write_bytes(b"not a safetensors file")
    foreign = _cli("train", "--average", str(start), str(end), "--out", str(tmp_path / "x"))
    assert foreign.returncode == 2 and "vae.safetensors of" in foreign.stderr
    assert not (tmp_path / "x").exists()
    taken = _cli("train", "--average", str(start), str(start), "--out", str(end))
    assert taken.returncode == 2 and "exists (give a new folder)" in taken.stderr
    (tmp_path / "file").write_text("")
    under_a_file = _cli("train", "--average", str(start), str(start), "--out",
                        str(tmp_path / "file" / "x"))
    assert under_a_file.returncode == 2
    assert under_a_file.stderr.strip().splitlines()[-1].endswith("file is a file; give a folder")


def test_the_removed_commands_name_their_replacements(tmp_path):
    for command, replacement in (("interpolate-weights", "volumesh train --average"),
                                 ("selector-ensemble", "volumesh train --selector-ensemble")):
        done = _cli(command, "a", "b", "--out", str(tmp_path / "x"), "--share", "0.5")
        assert done.returncode == 2
        line = done.stderr.strip().splitlines()[-1]
        assert line.startswith(f"volumesh: error: {command}: removed") and replacement in line
    assert not (tmp_path / "x").exists()
