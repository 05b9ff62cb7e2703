"""The shared training loop's parts: crops, the masked loss, its weights, the learning-rate
schedule and checkpoints."""

from dataclasses import replace
from itertools import pairwise

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.enhance.training.config import StageBudget
from pipeline.enhance.training.data import same_surface_mask
from pipeline.enhance.training.loop import (
    CropSampler,
    _learning_rate,
    checkpoint_from_bytes,
    checkpoint_to_bytes,
    fit,
    masked_mse,
    slope_weights,
)
from tests.pipeline.enhance.depth_pairs import ramp_pairs


def test_crops_are_flipped_or_transposed_windows_of_one_pair():
    pairs = ramp_pairs()
    sampler = CropSampler(pairs, crop=8, seed=3)
    deg, valid, clean, mask, side = sampler.batch(64, torch.device("cpu"))
    assert deg.shape == (64, 1, 8, 8) and side.shape == (64, 2, 8, 8)
    assert torch.allclose(clean - deg, torch.full_like(deg, 0.01), atol=1e-6)
    seen = set()
    for crop, m in zip(deg[:, 0].numpy(), mask[:, 0].numpy(), strict=True):
        i, y, x = (int(a[0]) for a in np.nonzero(pairs.degraded_n == crop.min()))
        window = pairs.degraded_n[i, y : y + 8, x : x + 8]
        variants = [np.rot90(w, k) for w in (window, window.T) for k in range(4)]
        matches = [k for k, v in enumerate(variants) if np.array_equal(v, crop)]
        assert matches, "a crop is no dihedral transform of a window"
        seen.add(matches[0])
        assert m.mean() >= 0.2  # crops mostly off the mask are redrawn
    assert len(seen) == 8  # every flip/transpose combination occurs


def test_a_tighter_surface_mask_drops_pixels_the_default_keeps_and_the_sampler_uses_it():
    pairs = ramp_pairs(1, 16)
    near = replace(pairs, degraded_n=pairs.degraded_n.copy())
    near.degraded_n[0, 3, 3] -= 0.03  # 0.04 from the clean render: kept at 0.05, not at 0.02
    default, tight = same_surface_mask(near), same_surface_mask(near, threshold_n=0.02)
    assert default[0, 3, 3] and not tight[0, 3, 3]
    assert tight.sum() == default.sum() - 1
    sampler = CropSampler(near, crop=16, seed=0, mask_threshold_n=0.02)
    _, _, _, mask, _ = sampler.batch(8, torch.device("cpu"))
    assert mask.sum() == 8 * tight.sum()  # the whole image is the one crop, in some flip


@settings(max_examples=25, deadline=None)
@given(
    a=st.floats(-3.0, 3.0), b=st.floats(-3.0, 3.0), offset=st.floats(-1.0, 1.0),
    power=st.sampled_from([0, 2, 4]),
)
def test_slope_weights_are_the_cos_of_a_planes_slant(a, b, offset, power):
    """An orthographic render of the plane z = a x + b y (x, y, z in image sides, the unit of
    normalised depth): every pixel off the border weighs (1 + a² + b²)^(-power/2), the
    power of the cos between its normal and the view."""
    res = 32
    t = torch.arange(res, dtype=torch.float64) / res
    plane = offset + a * t[None, :] + b * t[:, None]
    w = slope_weights(plane[None, None], res, power)[0, 0, 1:-1, 1:-1]
    expected = (1.0 + a * a + b * b) ** (-power / 2)
    assert torch.allclose(w, torch.full_like(w, expected), rtol=1e-9)


def test_masked_mse_counts_only_the_mask_in_residual_units():
    from pipeline.enhance.models.common import RESIDUAL_SCALE

    pred = torch.zeros(1, 1, 2, 2)
    target = torch.tensor([[[[1.0, 2.0], [3.0, 100.0]]]]) * RESIDUAL_SCALE
    mask = torch.tensor([[[[True, True], [True, False]]]])
    assert masked_mse(pred, target, mask).item() == pytest.approx((1 + 4 + 9) / 3)
    weight = torch.tensor([[[[1.0, 0.0], [0.0, 1.0]]]])
    assert masked_mse(pred, target, mask, weight).item() == pytest.approx(1.0)


@settings(max_examples=30, deadline=None)
@given(steps=st.integers(20, 5000), lr=st.floats(1e-5, 1e-2))
def test_learning_rate_warms_up_then_decays_to_a_twentieth(steps, lr):
    budget = StageBudget(steps, 1.0, lr)
    rates = [_learning_rate(budget, k) for k in range(steps + 1)]
    warm = max(1, steps // 20)
    assert rates[warm - 1] == pytest.approx(lr)  # the peak ends the warm-up
    assert all(a <= b + 1e-15 for a, b in pairwise(rates[:warm]))
    assert all(a >= b - 1e-15 for a, b in pairwise(rates[warm - 1 :]))
    assert rates[-1] == pytest.approx(0.05 * lr)


def test_fit_stops_at_its_step_budget_and_checkpoints_round_trip():
    torch.manual_seed(0)
    layer = torch.nn.Linear(1, 1)
    target = torch.ones(1, 1)
    rng = np.random.default_rng(0)
    saved = []
    log = fit("toy", {"layer": layer}, list(layer.parameters()),
              lambda: ((layer(torch.ones(1, 1)) - target) ** 2).mean(), rng,
              StageBudget(20, 1.0, 0.1), 10, None, saved.append, None)
    assert [c["step"] for c in saved] == [10, 20] and log[-1]["step"] == 20
    assert log[-1]["loss"] < log[0]["loss"]
    again = checkpoint_from_bytes(checkpoint_to_bytes(saved[-1]))
    assert torch.equal(again["modules"]["layer"]["weight"], layer.state_dict()["weight"])
    # A finished checkpoint resumes to no further steps.
    assert fit("toy", {"layer": layer}, list(layer.parameters()), lambda: 1 / 0, rng,
               StageBudget(20, 1.0, 0.1), 10, again, None, None) == log
