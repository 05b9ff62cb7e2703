from dataclasses import replace

import numpy as np
import pytest
import torch

from pipeline.enhance.models.vertex_gain import VertexGainConfig
from pipeline.enhance.training.data import procedural_meshes
from pipeline.enhance.training.gain import (
    GainExample,
    GainTrainConfig,
    gain_examples,
    gain_loss,
    train_gain,
    validate_gain,
)
from pipeline.enhance.update.vertex_gain import GAIN_FEATURES

TINY = GainTrainConfig(model=VertexGainConfig(hidden=8), with_procedural=True, draws_per_mesh=1,
                       edge_fraction=(0.03, 0.04), resolution=32, vertices_per_draw=500,
                       steps=5, batch=64)


def test_gain_loss_is_the_moved_vertices_mean_squared_distance():
    features = torch.tensor([[2.0, 0, 1, 1], [-1.0, 0, 1, 1]])
    target = torch.tensor([1.0, -1.0])
    assert gain_loss(torch.tensor([0.5, 1.0]), features, target) == 0.0
    assert gain_loss(torch.tensor([1.0, 0.0]), features, target) == pytest.approx(1.0)


def test_training_learns_to_trust_agreeing_views_and_not_disagreeing_ones():
    """Where the views agree (no spread) half the step is right, where they disagree none:
    the trained gains find both, which no single gain can."""
    rng = np.random.default_rng(0)
    n = 20_000
    step = rng.normal(size=n).astype(np.float32)
    agree = rng.random(n) < 0.5
    spread = np.where(agree, 0.05, 2.0).astype(np.float32) * rng.uniform(0.8, 1.2, n)
    features = np.stack([step, spread, np.full(n, 2.0), np.full(n, 3.0)], 1).astype(np.float32)
    target = np.where(agree, 0.5 * step, 0.0).astype(np.float32)
    config = GainTrainConfig(model=VertexGainConfig(hidden=16), steps=600, batch=1024, lr=3e-3)
    model, log = train_gain([GainExample("synthetic", features, target)], config, seed=0)
    assert log["steps"] == 600
    with torch.no_grad():
        gain = model(torch.from_numpy(features)).numpy()
    assert abs(np.median(gain[agree]) - 0.5) < 0.05
    assert np.median(gain[~agree]) < 0.1


def test_examples_and_validation_of_a_tiny_run():
    """Examples are the seen vertices of each draw, the same for every method; validation
    scores the fixed and the learned gains of each method on held-out draws."""
    meshes = procedural_meshes(np.random.default_rng(0), 3)
    examples = gain_examples(meshes[:2], TINY, None, np.random.default_rng(1))
    assert set(examples) == {"ldm", "regressor"}
    ldm, reg = examples["ldm"], examples["regressor"]
    assert len(ldm) == 2 and ldm[0].features.shape[1] == GAIN_FEATURES
    assert all(np.array_equal(a.target, b.target) for a, b in zip(ldm, reg, strict=True))
    assert all(np.all(e.features[:, 3] > 0) for e in ldm)  # seen by at least one view
    without = replace(TINY, with_procedural=False)
    assert gain_examples(meshes[:2], without, None, np.random.default_rng(1)) == {
        "ldm": [], "regressor": []}
    models = {m: train_gain(ex, TINY, seed=0)[0] for m, ex in examples.items()}
    figures = validate_gain(models, meshes[2:], TINY, None, np.random.default_rng(2))
    f = figures[meshes[2][0]]
    assert set(f) == {"presmoothed", "ldm_fixed_gain", "ldm_learned_gain",
                      "regressor_fixed_gain", "regressor_learned_gain"}
    assert all(np.isfinite(v) and v > 0 for v in f.values())
