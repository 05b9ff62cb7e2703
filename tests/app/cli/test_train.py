"""`volumesh train` through the real CLI: a tiny configuration end to end, pairs made by
worker processes."""

import json

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from pipeline.enhance.training.data import DataConfig, procedural_meshes
from pipeline.enhance.training.plan import training_pairs
from pipeline.io.mesh_io import write_ply

TINY_DATA = DataConfig(resolution=32, poses_per_mesh=3, views_per_pose=2,
                       edge_fraction=(0.03, 0.04))


def test_pairs_do_not_depend_on_the_number_of_workers():
    meshes = procedural_meshes(np.random.default_rng(0), 2)
    one = training_pairs(meshes, TINY_DATA, 7, workers=1)
    two = training_pairs(meshes, TINY_DATA, 7, workers=2)
    assert len(one.source) == 2 * 3 * 2
    for field in ("degraded_n", "noisy_n", "clean_n", "loss_mask", "edges"):
        assert np.array_equal(getattr(one, field), getattr(two, field)), field
    assert one.source == two.source


def _meshes(tmp_path):
    """Two procedural meshes written as files: the folder."""
    meshes = tmp_path / "meshes"
    meshes.mkdir(exist_ok=True)
    for name, mesh in procedural_meshes(np.random.default_rng(1), 2):
        write_ply(meshes / f"{name}.ply", mesh)
    return meshes


def _train_tiny(tmp_path, stages: str, *options: str, out_name: str = "run", workers: int = 1):
    """`volumesh train --config tiny` on two procedural meshes written as files: (result, out).

    One process makes the pairs unless `workers` says otherwise: each worker process is
    spawned and imports torch afresh (seconds apiece on two cores), so only `ldm_run` (the run
    through the CLI end to end) makes them in worker processes;
    `test_pairs_do_not_depend_on_the_number_of_workers` shows the pairs are the same."""
    from app.cli import app

    meshes = _meshes(tmp_path)
    out = tmp_path / out_name
    result = CliRunner().invoke(app, [
        "train", "--out", str(out), "--config", "tiny", "--meshes", str(meshes),
        "--procedural", "1", "--workers", str(workers), "--stages", stages, *options,
    ])
    return result, out


@pytest.fixture(scope="module")
def ldm_run(tmp_path_factory):
    """One tiny run of the regressor, VAE and LDM stages, its pairs made by two worker
    processes, read by several tests: its folder."""
    tmp_path = tmp_path_factory.mktemp("ldm-run")
    result, out = _train_tiny(tmp_path, "regressor,vae,ldm", workers=2)
    assert result.exit_code == 0, result.output
    return out


def test_train_tiny_writes_weights_and_report(ldm_run):
    out = ldm_run
    for name in ("regressor", "vae", "ldm"):
        assert (out / f"{name}.safetensors").stat().st_size > 0
    report = json.loads((out / "training.json").read_text())
    assert report["regressor"]["steps"] == 3 and report["vae"]["steps"] == 3
    assert "procedural-0" in report["data"]["train"]
    assert (out / "checkpoints" / "regressor.pt").is_file()
    # The VAE is trained on the regressor's estimate and scored beside it.
    assert "regressor" in report["vae"]["validation"]


def test_the_ldm_a_run_writes_carries_the_regressor_it_refines(ldm_run):
    from pipeline.enhance.weights.loading import weights_from_bytes

    out = ldm_run
    regressor, _ = weights_from_bytes((out / "regressor.safetensors").read_bytes())
    ldm, meta = weights_from_bytes((out / "ldm.safetensors").read_bytes())
    assert meta["refines_regressor"] == {"channels": [8, 16]}
    for key, value in regressor.items():
        assert torch.equal(ldm[f"refines.{key}"], value), key


def test_ldm_stages_without_a_regressor_are_refused_by_name_before_any_work(tmp_path):
    result, out = _train_tiny(tmp_path, "vae")
    assert result.exit_code != 0
    assert "refines the regressor" in str(result.exception)
    assert not (out / "training.json").exists()  # refused before the pairs were made


def test_a_meshes_folder_that_is_not_there_is_refused_before_any_work(tmp_path):
    from app.cli import app

    missing = tmp_path / "no-such-folder"
    result = CliRunner().invoke(app, ["train", "--out", str(tmp_path / "out"), "--config",
                                      "tiny", "--meshes", str(missing)])
    assert isinstance(result.exception, ValueError)
    assert str(result.exception) == f"--meshes: {missing} is not a folder"
    assert not (tmp_path / "out").exists()


def test_train_init_fine_tunes_given_weights_and_rejects_a_folder_without_them(tmp_path,
                                                                              ldm_run):
    from pipeline.enhance.weights.loading import weights_from_bytes

    result, second = _train_tiny(tmp_path, "regressor,finetune", "--init", str(ldm_run))
    assert result.exit_code == 0, result.output
    report = json.loads((second / "training.json").read_text())
    assert report["init"] == str(ldm_run)
    assert report["regressor"]["steps"] == 3 and report["finetune"]["steps"] == 3
    # Three more steps from the first run's weights: changed, but near them (a fresh
    # initialisation would be far).
    for name in ("regressor", "ldm"):
        before, _ = weights_from_bytes((ldm_run / f"{name}.safetensors").read_bytes())
        after, _ = weights_from_bytes((second / f"{name}.safetensors").read_bytes())
        moved = [float((after[k] - before[k]).abs().max()) for k in before]
        assert 0 < max(moved) < 0.05, name

    result, _ = _train_tiny(tmp_path, "regressor", "--init", str(_meshes(tmp_path)),
                            out_name="third")
    assert result.exit_code != 0
    assert "--init" in str(result.exception)


def test_train_selector_stage_alone_writes_its_weights(tmp_path):
    """The selector needs no depth pairs; its weights load and blend a mesh's twicings."""
    from pipeline.enhance import EnhanceConfig, enhance_mesh

    result, out = _train_tiny(tmp_path, "selector")
    assert result.exit_code == 0, result.output
    report = json.loads((out / "training.json").read_text())
    assert report["selector"]["steps"] == 5 and "train_pairs" not in report["data"]
    assert set(report["selector"]["validation"]) == set(report["data"]["validation"])
    _, mesh = procedural_meshes(np.random.default_rng(2), 1)[0]
    weights = {"selector": (out / "selector.safetensors").read_bytes()}
    blended = enhance_mesh(mesh, EnhanceConfig(method="classical", weights=weights,
                                               min_noise_ratio=0.0, remesh_iterations=0))
    assert blended.vertex_count == mesh.vertex_count
    assert not np.allclose(blended.vertices_m, mesh.vertices_m)


def test_the_shipped_model_card_gives_the_recipe_and_training_json_its_record():
    """The card is written by hand: what the networks are and the commands of their recipe;
    training.json keeps the machine record of the runs it names."""
    from importlib import resources

    weights = resources.files("pipeline.enhance.weights")
    report = json.loads(weights.joinpath("training.json").read_text())
    card = weights.joinpath("MODEL_CARD.md").read_text()
    for command in ("volumesh train --config large --stages selector",
                    "--stages gain --procedural 12", "volumesh train --average",
                    "--stages regressor,finetune,gain --mix mesh --loss-mask 0.02"):
        assert command in card, command
    assert "session" not in card
    assert report["averaged"]["finetune"]["validation"]["views"] == 24
    assert report["remasked"]["loss_mask_threshold_n"] == 0.02
    for stage in ("selector", "gain"):
        record = report["noise_mix"][stage]
        kinds = record["noise_kinds"] if stage == "selector" else record["config"]["noise_kinds"]
        assert kinds == ["uniform", "gaussian", "laplace"]


def test_mesh_mix_drops_only_the_sensor_degradations_and_unknown_mixes_are_refused(tmp_path):
    from dataclasses import asdict

    from app.cli import app
    from pipeline.enhance.training.data import with_mix

    mesh = with_mix(TINY_DATA, "mesh")
    changed = {k for k, v in asdict(mesh).items() if asdict(TINY_DATA)[k] != v}
    assert changed == {"kinect_probability", "hole_probability", "downup_probability"}
    assert mesh.kinect_probability == mesh.hole_probability == mesh.downup_probability == 0.0
    assert with_mix(TINY_DATA, "full") == TINY_DATA
    result = CliRunner().invoke(app, ["train", "--out", str(tmp_path), "--mix", "sensor"])
    assert result.exit_code != 0
    assert "--mix: 'sensor' is not one of full, mesh" in str(result.exception)


def test_learning_rate_and_loss_mask_options_reach_every_stage(tmp_path):
    result, out = _train_tiny(tmp_path, "regressor", "--lr", "2e-4", "--loss-mask", "0.02")
    assert result.exit_code == 0, result.output
    report = json.loads((out / "training.json").read_text())
    config = report["config"]
    assert config["loss_mask_threshold_n"] == 0.02 and report["regressor"]["lr"] == 2e-4
    assert {config[f"{s}_budget"]["lr"] for s in ("regressor", "vae", "ldm", "finetune")} == {
        2e-4
    }


def test_train_gain_stage_writes_a_gain_per_network(tmp_path):
    """The gain stage enhances with the --init networks (here the shipped ones) and writes a
    vertex gain network per method, which `enhance_mesh` loads from the weights given."""
    from dataclasses import replace
    from importlib import resources

    from pipeline.enhance import EnhanceConfig, enhance_mesh

    shipped = resources.files("pipeline.enhance.weights")
    result, out = _train_tiny(tmp_path, "gain", "--init", str(shipped))
    assert result.exit_code == 0, result.output
    report = json.loads((out / "training.json").read_text())
    assert set(report["gain"]["methods"]) == {"ldm", "regressor"}
    assert report["gain"]["methods"]["ldm"]["steps"] == 5
    assert set(report["gain"]["validation"]) == set(report["data"]["validation"])
    assert set(next(iter(report["gain"]["validation"].values()))) == {
        "presmoothed", "ldm_fixed_gain", "ldm_learned_gain", "regressor_fixed_gain",
        "regressor_learned_gain"}
    _, mesh = procedural_meshes(np.random.default_rng(2), 1)[0]
    weights = {"regressor_gain": (out / "regressor_gain.safetensors").read_bytes()}
    config = EnhanceConfig(method="regressor", resolution=32, min_noise_ratio=0,
                           remesh_iterations=0, weights=weights)
    shipped_gain = replace(config, weights=None)
    assert not np.allclose(enhance_mesh(mesh, config).vertices_m,
                           enhance_mesh(mesh, shipped_gain).vertices_m)


def test_selector_ensemble_writes_the_members_mean_and_names_a_missing_file(tmp_path):
    """`volumesh train --selector-ensemble` writes a selector whose weights are its members'
    mean; a member that is not there is one line and exit 2, and nothing is written."""
    import subprocess
    import sys
    from dataclasses import asdict

    import torch

    from pipeline.enhance.models.twicing_selector import SelectorConfig, TwicingSelector
    from pipeline.enhance.weights.loading import load_selector, weights_to_bytes

    config = SelectorConfig(iterations=(2, 5), pilot_iterations=3, feature_rings=(0,), hidden=4)
    paths = []
    for seed in (1, 2):
        torch.manual_seed(seed)
        paths.append(tmp_path / f"s{seed}.safetensors")
        paths[-1].write_bytes(weights_to_bytes(TwicingSelector(config).state_dict(),
                                               asdict(config)))

    def cli(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-c", "from app.cli import main; main()", *args],
                              capture_output=True, text=True, timeout=120)

    def ensemble(out, *members) -> subprocess.CompletedProcess:
        given = [arg for member in members for arg in ("--selector-ensemble", str(member))]
        return cli("train", "--out", str(out), *given)

    done = ensemble(tmp_path / "ensemble", *paths)
    assert done.returncode == 0, done.stderr
    out = tmp_path / "ensemble" / "selector.safetensors"
    x = torch.randn(20, config.blend.feature_count)
    with torch.no_grad():
        mean = torch.stack([load_selector(p.read_bytes())(x) for p in paths]).mean(dim=0)
        assert torch.allclose(load_selector(out.read_bytes())(x), mean, atol=1e-6)
    missing = ensemble(tmp_path / "x", paths[0], tmp_path / "nope.safetensors")
    assert missing.returncode == 2
    assert missing.stderr.strip().splitlines()[-1].endswith("nope.safetensors is not a file")
    foreign = tmp_path / "foreign.safetensors"
    foreign.write_bytes(b"not a safetensors file")
    wrong = ensemble(tmp_path / "x", paths[0], foreign)
    assert wrong.returncode == 2
    assert "foreign.safetensors is not a selector file" in wrong.stderr.strip().splitlines()[-1]
    twice = ensemble(tmp_path / "x", paths[0], paths[0])
    assert twice.returncode == 2 and "two or more different" in twice.stderr
    assert not (tmp_path / "x").exists()
