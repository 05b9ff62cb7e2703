import numpy as np
import pytest
import torch

from pipeline.enhance.models.twicing_selector import SelectorConfig, TwicingSelector
from pipeline.enhance.training.data import procedural_meshes
from pipeline.enhance.training.selector import (
    SelectorTrainConfig,
    blend_loss,
    selector_examples,
    train_selector,
    validate_selector,
)

BOX_AND_CYLINDER = slice(2, 4)


def test_selector_weights_are_convex_per_vertex():
    model = TwicingSelector(SelectorConfig(hidden=8))
    w = model(torch.randn(50, model.config.blend.feature_count) * 10)
    assert w.shape == (50, len(model.config.iterations))
    assert torch.all(w >= 0)
    assert torch.allclose(w.sum(dim=1), torch.ones(50))


def test_blend_loss_is_the_blends_mean_squared_distance():
    errors = torch.tensor([[1.0, -1.0], [2.0, 0.0]])
    assert blend_loss(torch.tensor([[0.5, 0.5], [0.0, 1.0]]), errors) == 0.0
    assert blend_loss(torch.tensor([[1.0, 0.0], [1.0, 0.0]]), errors) == pytest.approx(2.5)


def test_trained_selector_beats_adaptive_twicing_on_fresh_draws():
    """Trained briefly on noisy boxes and cylinders (flat faces, sharp edges), on new draws
    of them (another remesh and noise) its blend is closer to the truth than adaptive
    twicing's choice and than the best single count."""
    meshes = procedural_meshes(np.random.default_rng(0), 4)[BOX_AND_CYLINDER]
    config = SelectorTrainConfig(
        model=SelectorConfig(hidden=16), draws_per_mesh=2, edge_fraction=(0.02, 0.03),
        noise_to_edge=(1.5, 2.5), vertices_per_draw=4000, steps=400, batch=1024, lr=3e-3,
    )
    examples = selector_examples(meshes, config, np.random.default_rng(1))
    assert len(examples) == 4 and examples[0].errors.shape[1] == len(config.model.iterations)
    model, log = train_selector(examples, config, seed=0)
    assert log["steps"] == 400
    figures = validate_selector(model, meshes, config, np.random.default_rng(2))
    for f in figures.values():
        assert f["selector"] < 0.97 * f["adaptive_twicing"]
        assert f["selector"] < f["best_count"] < f["noisy"]
