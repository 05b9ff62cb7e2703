import numpy as np
import pytest
import torch

from pipeline.enhance.models.twicing_selector import (
    SelectorConfig,
    SelectorEnsemble,
    TwicingSelector,
)
from pipeline.enhance.weights.loading import (
    load_selector,
    selector_ensemble_to_bytes,
    weights_to_bytes,
)

SMALL = SelectorConfig(iterations=(2, 5, 10), pilot_iterations=5, feature_rings=(0, 3), hidden=8)


def _selector_bytes(seed: int, config: SelectorConfig = SMALL) -> bytes:
    from dataclasses import asdict

    torch.manual_seed(seed)
    return weights_to_bytes(TwicingSelector(config).state_dict(), asdict(config))


def _features(rows: int = 50) -> torch.Tensor:
    return torch.from_numpy(np.random.default_rng(0).normal(
        size=(rows, SMALL.blend.feature_count)).astype(np.float32))


def test_an_ensemble_weighs_by_the_mean_of_its_members_and_survives_its_bytes():
    parts = [_selector_bytes(seed) for seed in (1, 2, 3)]
    ensemble = load_selector(selector_ensemble_to_bytes(parts))
    assert isinstance(ensemble, SelectorEnsemble)
    x = _features()
    with torch.no_grad():
        weights = ensemble(x)
        mean = torch.stack([load_selector(p)(x) for p in parts]).mean(dim=0)
    assert torch.allclose(weights, mean, atol=1e-6)
    assert torch.all(weights >= 0) and torch.allclose(weights.sum(dim=1), torch.ones(len(x)))
    assert ensemble.config.blend == SMALL.blend


def test_members_must_weigh_the_same_candidates_and_not_be_ensembles():
    other = SelectorConfig(iterations=(2, 5, 20), pilot_iterations=5, feature_rings=(0, 3),
                           hidden=8)
    with pytest.raises(ValueError, match="different candidates"):
        selector_ensemble_to_bytes([_selector_bytes(1), _selector_bytes(2, other)])
    nested = selector_ensemble_to_bytes([_selector_bytes(1), _selector_bytes(2)])
    with pytest.raises(ValueError, match="itself an ensemble"):
        selector_ensemble_to_bytes([nested, _selector_bytes(3)])
