"""Named configurations and the budget edits the CLI applies to them."""

import pytest
from hypothesis import given
from hypothesis import strategies as st

from pipeline.enhance.training.config import CONFIGS, capped, scaled, with_lr


def _budgets(config):
    return [config.regressor_budget, config.vae_budget, config.ldm_budget, config.finetune_budget]


@given(name=st.sampled_from(sorted(CONFIGS)), factor=st.floats(0.01, 4.0))
def test_scaling_multiplies_every_stage_and_keeps_the_rest(name, factor):
    base = CONFIGS[name]
    out = scaled(base, factor)
    for a, b in zip(_budgets(base), _budgets(out), strict=True):
        assert b.steps == max(1, int(a.steps * factor))
        assert b.minutes == pytest.approx(a.minutes * factor) and b.lr == a.lr
    assert out.selector.steps == max(1, int(base.selector.steps * factor))
    assert out.data == base.data and out.crop == base.crop and out.batch == base.batch


def test_a_nonpositive_scale_is_refused():
    with pytest.raises(ValueError, match="budget scale"):
        scaled(CONFIGS["tiny"], 0.0)


def test_capping_and_learning_rate_touch_only_their_field():
    base = CONFIGS["small"]
    for a, b in zip(_budgets(base), _budgets(capped(base, 3.5)), strict=True):
        assert (b.steps, b.minutes, b.lr) == (a.steps, 3.5, a.lr)
    for a, b in zip(_budgets(base), _budgets(with_lr(base, 1e-4)), strict=True):
        assert (b.steps, b.minutes, b.lr) == (a.steps, a.minutes, 1e-4)
    assert capped(base, 3.5).selector == base.selector
