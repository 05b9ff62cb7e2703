"""`volumesh enhance-mesh` through the real CLI: the three methods, the options it takes and
the ones it refuses by name."""

import subprocess
import sys

import numpy as np
import pytest
from typer.testing import CliRunner

from pipeline.io.mesh_io import read_mesh, write_ply
from tests.pipeline.meshes import sphere

MAIN = "import sys; from app.cli import main; sys.argv[0] = 'volumesh'; main()"


def _noisy_file(tmp_path, seed: int = 1):
    from pipeline.enhance.training.data import noisy_along_normals

    src = tmp_path / "in.ply"
    write_ply(src, noisy_along_normals(sphere(0.5, 24), 0.01, np.random.default_rng(seed)))
    return src


def test_the_classical_method_smooths_a_noisy_mesh(tmp_path):
    from app.cli import app

    src, dst = _noisy_file(tmp_path), tmp_path / "out.ply"
    result = CliRunner().invoke(app, ["enhance-mesh", str(src), "--out", str(dst),
                                      "--method", "classical"])
    assert result.exit_code == 0, result.output
    spread = np.linalg.norm(read_mesh(dst).vertices_m, axis=1).std()
    assert spread < 0.6 * np.linalg.norm(read_mesh(src).vertices_m, axis=1).std()


@pytest.mark.parametrize(("method", "said"), [
    ("magic", "method: 'magic' is not one of regressor, ldm, classical"),
    ("taubin", "'classical' replaces the smoothers (one of regressor, ldm, classical)")])
def test_a_method_not_offered_is_one_line_and_exit_2(tmp_path, method: str, said: str):
    src = tmp_path / "in.ply"
    write_ply(src, sphere(0.5, 8))
    proc = subprocess.run([sys.executable, "-c", MAIN, "enhance-mesh", str(src), "--out",
                           str(tmp_path / "o.ply"), "--method", method],
                          capture_output=True, text=True)
    assert proc.returncode == 2
    assert proc.stderr.strip().startswith("volumesh: error: method") and said in proc.stderr


def test_enhance_mesh_defaults_are_the_pipelines():
    """The CLI spells its defaults out (importing the pipeline would slow `--help`); they must
    stay those of `EnhanceConfig`, which the shipped weights were chosen with."""
    import inspect

    from app.cli.enhance import enhance_mesh_command
    from pipeline.enhance import EnhanceConfig

    cli = {name: p.default for name, p in
           inspect.signature(enhance_mesh_command).parameters.items()}
    config = EnhanceConfig()
    for option in ("method", "steps", "seed", "device", "self_check"):
        assert cli[option] == getattr(config, option), option


@pytest.mark.parametrize("given", [
    ["--views", "14"], ["--resolution=64"], ["--strength", "0.3"], ["--iterations", "5"],
    ["--presmooth", "10"], ["--presmooth-passes", "1"], ["--fixed-presmooth"],
    ["--adaptive-presmooth"], ["--no-learned-presmooth"], ["--bounded-rings", "0"],
    ["--gain", "0.35"], ["--min-noise-ratio", "0"], ["--normal-filter", "0"],
    ["--remesh-ahead"], ["--remesh-after"], ["--ensemble", "4"]])
def test_a_removed_option_fails_naming_what_replaced_it(tmp_path, given: list[str]):
    from app.cli import app
    from app.cli.enhance import REMOVED_OPTIONS, removed_reason

    result = CliRunner().invoke(app, ["enhance-mesh", str(tmp_path / "missing.ply"), "--out",
                                      str(tmp_path / "o.ply"), *given])
    assert result.exit_code != 0 and isinstance(result.exception, ValueError)
    name = given[0].split("=")[0]
    declaration = next(d for d in REMOVED_OPTIONS if name in d.split("/"))
    assert str(result.exception) == f"{declaration}: {removed_reason(declaration)}"
    assert not (tmp_path / "o.ply").exists()


def test_a_removed_option_is_one_line_and_exit_2(tmp_path):
    proc = subprocess.run([sys.executable, "-c", MAIN, "enhance-mesh", "in.ply", "--out",
                           str(tmp_path / "o.ply"), "--gain", "0.35"],
                          capture_output=True, text=True)
    assert proc.returncode == 2
    assert proc.stderr.strip() == ("volumesh: error: --gain: removed; the per-vertex gain "
                                   "network sets each vertex's share of the correction")


def test_a_weights_folder_carries_its_gain_networks(tmp_path):
    """A gain network in a --weights folder is the one used; the result is deterministic."""
    import shutil
    from importlib import resources

    from app.cli import app

    src = _noisy_file(tmp_path)
    shipped = resources.files("pipeline.enhance.weights")
    folder = tmp_path / "weights"
    folder.mkdir()
    # The LDM's gain network standing in for the regressor's: another network, other moves.
    with resources.as_file(shipped.joinpath("ldm_gain.safetensors")) as ldm_gain:
        shutil.copy(ldm_gain, folder / "regressor_gain.safetensors")

    def run(*options: str) -> np.ndarray:
        dst = tmp_path / f"out{len(list(tmp_path.glob('out*')))}.ply"
        result = CliRunner().invoke(app, [
            "enhance-mesh", str(src), "--out", str(dst), "--method", "regressor", *options])
        assert result.exit_code == 0, result.output
        return read_mesh(dst).vertices_m

    def differ(a: np.ndarray, b: np.ndarray) -> bool:
        # The light remesh after the update may give other meshes other vertex counts.
        return a.shape != b.shape or not np.allclose(a, b)

    shipped_gains = run()
    assert not differ(shipped_gains, run())  # deterministic, so a difference below is the option's
    assert differ(shipped_gains, run("--weights", str(folder)))


def test_an_output_in_a_missing_folder_is_written_and_a_folder_refused_before_the_work(
        tmp_path):
    from app.cli import app

    src = tmp_path / "in.ply"
    write_ply(src, sphere(0.5, 8))
    nested = tmp_path / "new" / "folder" / "out.ply"
    made = CliRunner().invoke(app, ["enhance-mesh", str(src), "--out", str(nested),
                                    "--method", "classical"])
    assert made.exit_code == 0, made.output
    assert read_mesh(nested).face_count > 0
    # A folder given as the output: refused before the (long) enhancement, not after it:
    # before the input is even read.
    missing, taken = tmp_path / "missing.ply", tmp_path / "taken.ply"
    taken.mkdir()
    refused = CliRunner().invoke(app, ["enhance-mesh", str(missing), "--out", str(taken)])
    assert isinstance(refused.exception, ValueError)
    assert "--out:" in str(refused.exception) and "is a directory" in str(refused.exception)


def test_the_output_is_written_by_its_suffix_and_others_refused_before_the_work(tmp_path):
    from app.cli import app
    from pipeline.io.gltf_read import decode_glb

    src = tmp_path / "in.ply"
    write_ply(src, sphere(0.5, 8))
    glb = tmp_path / "out.glb"
    result = CliRunner().invoke(app, ["enhance-mesh", str(src), "--out", str(glb),
                                      "--method", "classical"])
    assert result.exit_code == 0, result.output
    assert glb.read_bytes()[:4] == b"glTF"
    assert f"wrote {glb} (" in result.output and "classical" in result.output
    assert decode_glb(glb.read_bytes()).face_count > 0
    refused = CliRunner().invoke(app, ["enhance-mesh", str(tmp_path / "missing.ply"),
                                       "--out", str(tmp_path / "out.obj")])
    assert isinstance(refused.exception, ValueError)
    assert str(refused.exception) == f"--out: {tmp_path / 'out.obj'} must end in .glb or .ply"


def test_a_clean_mesh_is_written_unchanged_by_the_decision_told(tmp_path, monkeypatch):
    """Below the noise gate the CLI says so and writes the mesh as it read it, by that
    decision alone: `enhance_mesh`, whose own gate measures again (in torch on a GPU), is not
    run, so the two cannot fall either side of the line."""
    import pipeline.enhance
    from app.cli import app

    def not_run(*args, **kwargs):
        raise AssertionError("enhance_mesh ran on a clean mesh")

    monkeypatch.setattr(pipeline.enhance, "enhance_mesh", not_run)
    clean = sphere(0.5, 24)
    src, dst = tmp_path / "in.ply", tmp_path / "out.ply"
    write_ply(src, clean)
    result = CliRunner().invoke(app, ["enhance-mesh", str(src), "--out", str(dst)])
    assert result.exit_code == 0, result.output
    assert "is below the noise gate, 0.05: written unchanged" in result.output
    np.testing.assert_array_equal(read_mesh(dst).vertices_m, read_mesh(src).vertices_m)


def test_the_self_check_tells_its_decision(tmp_path):
    """`--self-check` says what it measured on the simulated copy and which result it kept;
    without it nothing of the kind is said."""
    from app.cli import app
    from pipeline.enhance.training.data import noisy_along_normals

    src = tmp_path / "noisy.ply"
    write_ply(src, noisy_along_normals(sphere(), 0.01, np.random.default_rng(0)))

    def said(*options: str) -> str:
        result = CliRunner().invoke(app, [
            "enhance-mesh", str(src), "--out", str(tmp_path / "out.ply"), "--method",
            "regressor", *options])
        assert result.exit_code == 0, result.output
        return result.output

    told = [line for line in said("--self-check").splitlines() if "self-check" in line]
    assert len(told) == 1
    assert "mm with the networks" in told[0] and " kept" in told[0]
    assert "self-check" not in said()
