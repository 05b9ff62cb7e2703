"""A tiny configuration trains for a few steps, resumes, and its weights enhance a mesh."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from pipeline.enhance import EnhanceConfig, enhance_mesh
from pipeline.enhance.pipelines.depth_ldm import (
    LDMModels,
    enhance_depth_ldm,
    latent_shape,
    sample_depth,
)
from pipeline.enhance.training.config import CONFIGS, StageBudget
from pipeline.enhance.training.data import (
    DataConfig,
    make_pairs,
    procedural_meshes,
    same_surface_mask,
)
from pipeline.enhance.training.loop import checkpoint_from_bytes, checkpoint_to_bytes
from pipeline.enhance.training.stages import train_finetune, train_ldm, train_regressor, train_vae
from pipeline.enhance.weights.loading import weights_from_bytes, weights_to_bytes
from tests.pipeline.enhance.depth_pairs import ramp_pairs
from tests.pipeline.meshes import sphere

TINY = CONFIGS["tiny"]


@pytest.fixture(scope="module")
def pairs():
    meshes = procedural_meshes(np.random.default_rng(0), 2)
    cfg = DataConfig(resolution=48, poses_per_mesh=1, views_per_pose=2, edge_fraction=(0.03, 0.04))
    return make_pairs(meshes, cfg, 0)


def test_pairs_are_degraded_copies(pairs):
    assert pairs.degraded_n.shape == pairs.clean_n.shape == (4, 48, 48)
    diff = np.abs(pairs.degraded_n - pairs.clean_n)[pairs.loss_mask]
    assert 0 < np.median(diff) < 0.05
    assert pairs.source == ("procedural-0",) * 2 + ("procedural-1",) * 2


def test_light_noise_poses_degrade_less():
    meshes = procedural_meshes(np.random.default_rng(1), 1)
    base = DataConfig(resolution=48, poses_per_mesh=2, views_per_pose=2, edge_fraction=(0.03, 0.04),
                      kinect_probability=0.0, hole_probability=0.0, downup_probability=0.0)

    def median_change(light: float) -> float:
        p = make_pairs(meshes, replace(base, light_noise_probability=light), 0)
        return float(np.median(np.abs(p.noisy_n - p.clean_n)[p.loss_mask]))

    heavy, light = median_change(0.0), median_change(1.0)
    assert 0 < light < 0.5 * heavy


def test_presmoothed_base_is_closer_to_the_clean_depth_under_heavy_noise():
    """The networks' base (the render of the pre-smoothed noisy mesh) has averaged most noise
    away; the noisy render rides along."""
    meshes = procedural_meshes(np.random.default_rng(2), 1)
    cfg = DataConfig(resolution=64, poses_per_mesh=1, views_per_pose=3, edge_fraction=(0.02, 0.02),
                     noise_fraction=(0.02, 0.02), light_noise_probability=0.0,
                     kinect_probability=0.0, hole_probability=0.0, downup_probability=0.0)
    p = make_pairs(meshes, cfg, 0)

    def rms(a: np.ndarray) -> float:
        inner = p.loss_mask & (np.abs(a - p.clean_n) < 0.05)
        return float(np.sqrt(np.mean((a - p.clean_n)[inner] ** 2)))

    assert rms(p.degraded_n) < 0.6 * rms(p.noisy_n)


def test_regressor_trains_and_resumes_where_it_stopped(pairs):
    saved = []
    cfg = replace(TINY, regressor_budget=StageBudget(4, 1.0), checkpoint_every=2)
    _, log = train_regressor(pairs, cfg, 0, torch.device("cpu"), on_checkpoint=saved.append)
    assert [c["step"] for c in saved] == [2, 4]
    assert all(np.isfinite(e["loss"]) for e in log)
    cfg6 = replace(cfg, regressor_budget=StageBudget(6, 1.0))
    more = []
    stored = checkpoint_from_bytes(checkpoint_to_bytes(saved[0]))  # as the CLI stores it
    train_regressor(pairs, cfg6, 0, torch.device("cpu"), resume=stored, on_checkpoint=more.append)
    assert [c["step"] for c in more] == [4, 6]


def test_a_resumed_run_ends_where_an_uninterrupted_one_does(pairs):
    """Weights, optimiser, torch's and the crop sampler's random state all come back."""
    cfg = replace(TINY, regressor_budget=StageBudget(4, 1.0), checkpoint_every=2)
    saved: list[bytes] = []  # serialised at once, as the CLI does: state dicts are live views

    def keep(ck):
        saved.append(checkpoint_to_bytes(ck))

    whole, _ = train_regressor(pairs, cfg, 0, torch.device("cpu"), on_checkpoint=keep)
    stored = checkpoint_from_bytes(saved[0])
    resumed, _ = train_regressor(pairs, cfg, 0, torch.device("cpu"), resume=stored)
    for k, v in whole.state_dict().items():
        assert torch.equal(v, resumed.state_dict()[k]), k


def test_weights_round_trip_with_config():
    state = {"a": torch.arange(3.0)}
    got, cfg = weights_from_bytes(weights_to_bytes(state, {"channels": [8, 16]}))
    assert torch.equal(got["a"], state["a"]) and cfg == {"channels": [8, 16]}


def test_tiny_models_enhance_a_mesh_deterministically(pairs):
    from pipeline.enhance.weights.loading import ldm_to_bytes

    dev = torch.device("cpu")
    reg, _ = train_regressor(pairs, TINY, 0, dev)
    vae, _ = train_vae(pairs, TINY, 0, dev, refines=reg)
    unet, control, _ = train_ldm(pairs, vae, TINY, 0, dev, refines=reg)
    models, _ = train_finetune(pairs, LDMModels(vae, unet, control, reg), TINY, 0, dev)
    weights = {
        "regressor": weights_to_bytes(
            reg.state_dict(), {"channels": list(TINY.regressor.channels)}
        ),
        "vae": weights_to_bytes(models.vae.state_dict(), {"channels": list(TINY.vae.channels)}),
        "ldm": ldm_to_bytes(models, {"channels": list(TINY.unet.channels),
                                     "emb_dim": TINY.unet.emb_dim}),
    }
    mesh = sphere(0.5, 12)
    # No light remesh: the checks below compare vertex by vertex.
    base = EnhanceConfig(views=6, resolution=32, steps=2, weights=weights, remesh_iterations=0)
    a = enhance_mesh(mesh, base)
    b = enhance_mesh(mesh, base)
    assert np.array_equal(a.vertices_m, b.vertices_m)
    assert np.array_equal(a.faces, mesh.faces)
    c = enhance_mesh(mesh, replace(base, method="regressor"))
    assert np.all(np.isfinite(c.vertices_m))
    # Moves are capped: nothing leaves the neighbourhood of the sphere.
    r = np.linalg.norm(a.vertices_m, axis=1)
    assert np.all(np.abs(r - np.linalg.norm(mesh.vertices_m, axis=1)) < 0.04)


def test_finetuning_trains_every_part_through_the_sampler(pairs):
    dev = torch.device("cpu")
    vae, _ = train_vae(pairs, TINY, 0, dev)
    unet, control, _ = train_ldm(pairs, vae, TINY, 0, dev)
    before = {
        name: {k: v.clone() for k, v in part.state_dict().items()}
        for name, part in (("vae", vae), ("unet", unet), ("controlnet", control))
    }
    cfg = replace(TINY, finetune_budget=StageBudget(4, 1.0, 1e-3), finetune_steps=(2,))
    models, log = train_finetune(pairs, LDMModels(vae, unet, control), cfg, 0, dev)
    assert log and all(np.isfinite(e["loss"]) for e in log)
    parts = (("vae", models.vae), ("unet", models.unet), ("controlnet", models.controlnet))
    for name, part in parts:
        after = part.state_dict()
        floats = [k for k, v in before[name].items() if v.is_floating_point()]
        changed = [k for k in floats if not torch.equal(before[name][k], after[k])]
        assert changed, f"fine-tuning left the {name} untouched"
    # What fine-tuning differentiates is what inference runs: same noise, same depth.
    d = torch.from_numpy(pairs.degraded_n[:2, None])
    v = torch.from_numpy(pairs.degraded_valid[:2, None])
    gen = torch.Generator().manual_seed(5)
    noise = torch.randn(latent_shape(d), generator=gen)
    with torch.no_grad():
        trained = sample_depth(models, d, v, 2, 0.5, noise)
    assert torch.equal(trained, enhance_depth_ldm(models, d, v, 2, 0.5, 5))


def test_training_meshes_are_remeshed_isotropically():
    from pipeline.enhance.training.data import isotropic

    mesh = procedural_meshes(np.random.default_rng(3), 5)[2][1]  # a stretched box
    out = isotropic(mesh, 0.05)
    edges = np.concatenate([out.faces[:, [0, 1]], out.faces[:, [1, 2]], out.faces[:, [2, 0]]])
    lengths = np.linalg.norm(out.vertices_m[edges[:, 0]] - out.vertices_m[edges[:, 1]], axis=1)
    assert abs(lengths.mean() / 0.05 - 1.0) < 0.25
    assert lengths.std() / lengths.mean() < 0.35


def test_bad_config_is_named():
    mesh = sphere(0.5, 8)
    with pytest.raises(ValueError, match="method"):
        enhance_mesh(mesh, EnhanceConfig(method="magic"))
    with pytest.raises(ValueError, match="strength"):
        enhance_mesh(mesh, EnhanceConfig(strength=0.0))


def test_half_precision_weights_load_as_float32():
    state = {"w": torch.tensor([0.1, 1.0 / 3.0]), "n": torch.tensor([3])}
    got, _ = weights_from_bytes(weights_to_bytes(state, {}, half=True))
    assert got["w"].dtype == torch.float32 and got["n"].dtype == torch.int64
    assert torch.allclose(got["w"], state["w"], rtol=1e-3)


def test_vae_weights_reload_with_their_config():
    """What `volumesh train --resume` does with a finished VAE stage."""
    from dataclasses import asdict

    from pipeline.enhance.models.vae import DepthVAE, VAEConfig
    from pipeline.enhance.weights.loading import load_vae

    cfg = VAEConfig(channels=(8, 8, 16, 16), initial_logvar=-3.0)
    vae = DepthVAE(cfg)
    vae.latent_scale.fill_(2.5)
    again = load_vae(weights_to_bytes(vae.state_dict(), asdict(cfg)))
    assert float(again.latent_scale) == 2.5
    assert torch.equal(again.to_moments.weight, vae.to_moments.weight)


def test_coloured_poses_give_edges_and_uncoloured_none():
    meshes = procedural_meshes(np.random.default_rng(2), 1)
    base = DataConfig(resolution=64, poses_per_mesh=2, views_per_pose=2, edge_fraction=(0.03, 0.04))
    coloured = make_pairs(meshes, replace(base, color_probability=1.0), 0)
    plain = make_pairs(meshes, replace(base, color_probability=0.0), 0)
    assert not plain.edges.any()
    assert coloured.edges.shape == coloured.degraded_n.shape
    assert all(coloured.edges[k].any() for k in range(len(coloured.source)))
    assert not (coloured.edges & ~coloured.degraded_valid).any()  # only on the surface


def test_surface_mask_drops_pixels_where_either_input_sees_another_surface():
    pairs = ramp_pairs(1, 8)
    far = replace(pairs, noisy_n=pairs.noisy_n.copy(), degraded_n=pairs.degraded_n.copy())
    far.noisy_n[0, 0, 0] += 0.2  # the noisy render sees another surface here
    far.degraded_n[0, 1, 1] += 0.2  # and the base here
    far.noisy_n[0, 2, 2] = 1.0  # no noisy hit: only the base counts
    mask = same_surface_mask(far)
    assert not mask[0, 0, 0] and not mask[0, 1, 1] and mask[0, 2, 2]
    assert mask.sum() == pairs.loss_mask.sum() - 2


def test_bulk_scores_leave_out_what_the_tight_mask_drops(pairs):
    from pipeline.enhance.training.validate import depth_scores

    idx = np.arange(len(pairs.source))
    pred = pairs.clean_n[idx].copy()
    inside = same_surface_mask(pairs, idx, 0.02)
    pred[inside] += 0.001
    scores = depth_scores(pred, pairs, idx)
    assert scores["bulk_rmse_permille"] == pytest.approx(1.0, rel=1e-3)
    # Pixels between the two thresholds are exact here, so the default score is smaller.
    between = same_surface_mask(pairs, idx) & ~inside
    expected = np.sqrt(inside.sum() / (inside.sum() + between.sum()))
    assert scores["rmse_permille"] == pytest.approx(expected, rel=1e-3)


def _zero_correction_ldm(pairs, refines=None) -> LDMModels:
    """An untrained LDM whose decoder adds nothing to its guide."""
    from pipeline.enhance.models.controlnet import ControlNet
    from pipeline.enhance.models.unet import LatentUNet
    from pipeline.enhance.models.vae import DepthVAE

    torch.manual_seed(0)
    vae = DepthVAE(TINY.vae)
    torch.nn.init.zeros_(vae.conv_out.weight)
    torch.nn.init.zeros_(vae.conv_out.bias)
    return LDMModels(vae.eval(), LatentUNet(TINY.unet).eval(), ControlNet(TINY.unet).eval(),
                     refines)


def test_a_refining_ldm_corrects_the_regressors_estimate_not_the_base(pairs):
    """With `refines`, everything the LDM adds is added to the regressor's output: an LDM
    that adds nothing returns exactly the regressor's estimate (and the base without)."""
    from pipeline.enhance.models.common import side_inputs

    reg, _ = train_regressor(pairs, TINY, 0, torch.device("cpu"))
    d = torch.from_numpy(pairs.degraded_n[:2, None])
    v = torch.from_numpy(pairs.degraded_valid[:2, None])
    e = torch.from_numpy(pairs.edges[:2, None])
    side = side_inputs(e, torch.from_numpy(pairs.noisy_n[:2, None]), d, v)
    with torch.no_grad():
        estimate = reg(d, v, side)
    assert not torch.allclose(estimate, d)
    alone = enhance_depth_ldm(_zero_correction_ldm(pairs), d, v, 2, 0.5, 0, side)
    refining = enhance_depth_ldm(_zero_correction_ldm(pairs, reg), d, v, 2, 0.5, 0, side)
    assert torch.equal(alone, d)
    assert torch.equal(refining, estimate)


def test_finetuning_a_refining_ldm_leaves_its_regressor_alone(pairs):
    dev = torch.device("cpu")
    reg, _ = train_regressor(pairs, TINY, 0, dev)
    before = {k: v.clone() for k, v in reg.state_dict().items()}
    cfg = replace(TINY, finetune_budget=StageBudget(3, 1.0, 1e-3))
    models, _ = train_finetune(pairs, _zero_correction_ldm(pairs, reg), cfg, 0, dev)
    assert all(torch.equal(before[k], v) for k, v in models.refines.state_dict().items())
    assert models.vae.conv_out.weight.abs().max() > 0  # the LDM itself did train


def test_a_refining_ldm_round_trips_through_its_bytes_with_its_regressor(pairs):
    from pipeline.enhance.weights.loading import ldm_to_bytes, load_ldm

    dev = torch.device("cpu")
    reg, _ = train_regressor(pairs, TINY, 0, dev)
    vae, _ = train_vae(pairs, TINY, 0, dev, refines=reg)
    unet, control, _ = train_ldm(pairs, vae, TINY, 0, dev, refines=reg)
    models = LDMModels(vae, unet, control, reg)
    unet_cfg = {"channels": list(TINY.unet.channels), "emb_dim": TINY.unet.emb_dim}
    vae_bytes = weights_to_bytes(vae.state_dict(), {"channels": list(TINY.vae.channels)})
    again = load_ldm(vae_bytes, ldm_to_bytes(models, unet_cfg))
    assert again.refines is not None and again.refines.config == reg.config
    d = torch.from_numpy(pairs.degraded_n[:2, None])
    v = torch.from_numpy(pairs.degraded_valid[:2, None])
    assert torch.equal(enhance_depth_ldm(models, d, v, 2, 0.5, 3),
                       enhance_depth_ldm(again, d, v, 2, 0.5, 3))
    plain = load_ldm(vae_bytes, ldm_to_bytes(replace(models, refines=None), unet_cfg))
    assert plain.refines is None


def test_depth_scores_normal_error_discounts_slanted_pixels(pairs):
    """A uniform depth offset is the plain RMSE everywhere; along the normals, as the mesh
    update sees it, slanted pixels count for less, so it is smaller but of its size."""
    from pipeline.enhance.training.validate import depth_scores

    idx = np.arange(len(pairs.source))
    scores = depth_scores(pairs.clean_n[idx] + 0.002, pairs, idx)
    assert scores["rmse_permille"] == pytest.approx(2.0, rel=1e-4)
    assert 0.5 < scores["normal_rmse_permille"] < 2.0
    assert depth_scores(pairs.clean_n[idx], pairs, idx)["normal_rmse_permille"] == 0.0
