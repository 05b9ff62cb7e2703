"""`volumesh enhance-mesh` through the real CLI (baseline methods need no weights)."""

import numpy as np
from typer.testing import CliRunner

from pipeline.io.mesh_io import read_mesh, write_ply
from tests.pipeline.enhance.conftest import sphere


def test_enhance_mesh_smooths_a_noisy_mesh(tmp_path):
    from app.cli import app
    from pipeline.enhance.training.data import noisy_along_normals

    noisy = noisy_along_normals(sphere(0.5, 24), 0.01, np.random.default_rng(1))
    src, dst = tmp_path / "in.ply", tmp_path / "out.ply"
    write_ply(src, noisy)
    result = CliRunner().invoke(
        app,
        ["enhance-mesh", str(src), "--out", str(dst), "--method", "taubin", "--iterations", "5"],
    )
    assert result.exit_code == 0, result.output
    out = read_mesh(dst)
    assert out.face_count == noisy.face_count
    spread = np.linalg.norm(out.vertices_m, axis=1).std()
    assert spread < 0.6 * np.linalg.norm(noisy.vertices_m, axis=1).std()


def test_unknown_method_is_one_line_and_exit_2(tmp_path):
    import subprocess
    import sys

    src = tmp_path / "in.ply"
    write_ply(src, sphere(0.5, 8))
    code = "import sys; from app.cli import main; sys.argv[0] = 'volumesh'; main()"
    proc = subprocess.run(
        [
            sys.executable,
            "-c",
            code,
            "enhance-mesh",
            str(src),
            "--out",
            str(tmp_path / "o.ply"),
            "--method",
            "magic",
        ],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip().startswith("volumesh: error: method")


def test_enhance_mesh_defaults_are_the_pipelines():
    """The CLI spells its defaults out (importing the pipeline would slow `--help`); they must
    stay those of `EnhanceConfig`, which the shipped weights were chosen with."""
    import inspect

    from app.cli.enhance import enhance_mesh_command
    from pipeline.enhance import EnhanceConfig

    cli = {name: p.default for name, p in
           inspect.signature(enhance_mesh_command).parameters.items()}
    config = EnhanceConfig()
    pairs = {"method": "method", "views": "views", "resolution": "resolution", "steps": "steps",
             "strength": "strength", "iterations": "iterations",
             "presmooth": "presmooth_iterations", "presmooth_passes": "presmooth_passes",
             "adaptive": "presmooth_adaptive", "learned": "presmooth_learned",
             "min_noise_ratio": "min_noise_ratio", "seed": "seed", "ensemble": "ensemble",
             "device": "device", "remesh_ahead": "remesh_ahead"}
    for option, field in pairs.items():
        assert cli[option] == getattr(config, field), option
    assert cli["bounded_rings"] == config.bounded_noise.rings
    # No --gain: the learned per-vertex gains; --gain G: G everywhere.
    assert cli["gain"] is None and config.learned_gain


def test_a_fixed_gain_replaces_the_learned_gains_and_weights_folders_carry_gains(tmp_path):
    """`--gain G` follows G of the correction everywhere, the default each vertex's learned
    share; a gain network in a --weights folder is the one used."""
    import shutil
    from importlib import resources

    from app.cli import app
    from pipeline.enhance.training.data import noisy_along_normals

    noisy = noisy_along_normals(sphere(0.5, 24), 0.01, np.random.default_rng(1))
    src = tmp_path / "in.ply"
    write_ply(src, noisy)
    shipped = resources.files("pipeline.enhance.weights")
    folder = tmp_path / "weights"
    folder.mkdir()
    # The LDM's gain network standing in for the regressor's: another network, other moves.
    with resources.as_file(shipped.joinpath("ldm_gain.safetensors")) as ldm_gain:
        shutil.copy(ldm_gain, folder / "regressor_gain.safetensors")

    def run(*options: str) -> np.ndarray:
        dst = tmp_path / f"out{len(list(tmp_path.glob('out*')))}.ply"
        result = CliRunner().invoke(app, [
            "enhance-mesh", str(src), "--out", str(dst), "--method", "regressor",
            "--resolution", "64", "--min-noise-ratio", "0", *options])
        assert result.exit_code == 0, result.output
        return read_mesh(dst).vertices_m

    def differ(a: np.ndarray, b: np.ndarray) -> bool:
        # The light remesh after the update may give other meshes other vertex counts.
        return a.shape != b.shape or not np.allclose(a, b)

    learned = run()
    assert not differ(learned, run())  # deterministic, so a difference below is the option's
    assert differ(learned, run("--gain", "0.35"))
    assert differ(learned, run("--weights", str(folder)))
    assert differ(learned, run("--normal-filter", "0"))
    # The CPU remeshes after the update by default; ahead is the GPU's default.
    assert not differ(learned, run("--remesh-after"))
    assert differ(learned, run("--remesh-ahead"))


def test_an_output_in_a_missing_folder_is_written_and_a_folder_refused_before_the_work(
        tmp_path):
    from app.cli import app

    src = tmp_path / "in.ply"
    write_ply(src, sphere(0.5, 8))
    nested = tmp_path / "new" / "folder" / "out.ply"
    made = CliRunner().invoke(app, ["enhance-mesh", str(src), "--out", str(nested),
                                    "--method", "taubin", "--iterations", "2"])
    assert made.exit_code == 0, made.output
    assert read_mesh(nested).face_count == sphere(0.5, 8).face_count
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
                                      "--method", "taubin", "--iterations", "2"])
    assert result.exit_code == 0, result.output
    assert glb.read_bytes()[:4] == b"glTF"
    assert f"wrote {glb} (" in result.output and "taubin" in result.output
    assert decode_glb(glb.read_bytes()).face_count == sphere(0.5, 8).face_count
    refused = CliRunner().invoke(app, ["enhance-mesh", str(tmp_path / "missing.ply"),
                                       "--out", str(tmp_path / "out.obj")])
    assert isinstance(refused.exception, ValueError)
    assert str(refused.exception) == f"--out: {tmp_path / 'out.obj'} must end in .glb or .ply"


def test_a_clean_mesh_is_written_unchanged_by_the_decision_told(tmp_path, monkeypatch):
    """Below --min-noise-ratio the CLI says so and writes the mesh as it read it, by that
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
    assert "is below --min-noise-ratio 0.05: written unchanged" in result.output
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
            "regressor", "--resolution", "64", "--min-noise-ratio", "0", *options])
        assert result.exit_code == 0, result.output
        return result.output

    told = [line for line in said("--self-check").splitlines() if "self-check" in line]
    assert len(told) == 1
    assert "mm with the networks" in told[0] and " kept" in told[0]
    assert "self-check" not in said()
