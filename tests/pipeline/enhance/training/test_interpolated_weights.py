"""The weight-space average of two trainings of a network (`interpolated_weights`)."""

import pytest
import torch

from pipeline.enhance.models.regressor import RegressorConfig, ResidualUNet
from pipeline.enhance.weights.loading import (
    interpolated_weights,
    load_regressor,
    regressor_to_bytes,
)


def _regressor_bytes(seed: int, channels: tuple[int, ...] = (4, 8)) -> bytes:
    torch.manual_seed(seed)
    return regressor_to_bytes(ResidualUNet(RegressorConfig(channels=channels)))


def test_each_tensor_lies_at_the_share_of_the_way_from_start_to_end():
    start, end = _regressor_bytes(1), _regressor_bytes(2)
    a, b = load_regressor(start).state_dict(), load_regressor(end).state_dict()
    for share in (0.0, 0.25, 1.0):
        mixed = load_regressor(interpolated_weights(start, end, share)).state_dict()
        for k, v in mixed.items():
            want = ((1 - share) * a[k] + share * b[k]).half().float()
            assert torch.allclose(v, want, atol=2e-3, rtol=0), k
    half_way = load_regressor(interpolated_weights(start, end, 0.5)).state_dict()
    assert any(not torch.equal(half_way[k], a[k]) and not torch.equal(half_way[k], b[k])
               for k in a)


def test_two_different_networks_are_refused():
    with pytest.raises(ValueError, match="different networks"):
        interpolated_weights(_regressor_bytes(1), _regressor_bytes(1, (4, 8, 16)), 0.5)
