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


def test_the_shipped_networks_average_with_a_run_started_from_them(tmp_path):
    """A fine-tuning run from the shipped weights (`--init`) writes its networks' configs as
    the trainer spells them; the shipped files must read as the same networks."""
    from dataclasses import asdict

    from pipeline.enhance.models.vae import VAEConfig
    from pipeline.enhance.weights import shipped_bytes
    from pipeline.enhance.weights.loading import load_vae, weights_from_bytes, weights_to_bytes

    shipped = tmp_path / "shipped"
    shipped.mkdir()
    for name in ("regressor", "vae", "ldm"):
        (shipped / f"{name}.safetensors").write_bytes(shipped_bytes(name))
    run = tmp_path / "run"
    run.mkdir()
    vae = load_vae(shipped_bytes("vae"))
    _, shipped_config = weights_from_bytes(shipped_bytes("vae"))
    as_trained = VAEConfig(channels=tuple(shipped_config["channels"]),
                           initial_logvar=shipped_config["initial_logvar"])
    (run / "vae.safetensors").write_bytes(weights_to_bytes(vae.state_dict(), asdict(as_trained)))
    for name in ("regressor", "ldm"):
        (run / f"{name}.safetensors").write_bytes(shipped_bytes(name))
    done = _cli("train", "--average", str(shipped), str(run), "--out", str(tmp_path / "mixed"))
    assert done.returncode == 0, done.stderr
    mixed = load_vae((tmp_path / "mixed" / "vae.safetensors").read_bytes()).state_dict()
    for k, v in vae.state_dict().items():
        assert torch.equal(mixed[k], v), k
