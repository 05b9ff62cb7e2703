import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.enhance.schedulers import ddim
from pipeline.enhance.schedulers.ddpm import DDPMSchedule


def test_schedule_decreases_from_near_one():
    s = DDPMSchedule()
    a = s.alphas_cumprod
    assert a.shape == (1000,)
    assert np.all(np.diff(a) < 0)
    assert 0.99 < a[0] < 1.0 and a[-1] < 0.01
    with pytest.raises(ValueError, match="num_train_steps"):
        DDPMSchedule(num_train_steps=1)


def test_timesteps_follow_strength_and_steps():
    s = DDPMSchedule()
    ts = ddim.timesteps(s, 4, 0.5)
    assert ts[0] == 499 and len(ts) == 4 and np.all(np.diff(ts) < 0)
    assert list(ddim.timesteps(s, 1, 0.3)) == [299]
    with pytest.raises(ValueError, match="strength"):
        ddim.timesteps(s, 4, 0.0)
    with pytest.raises(ValueError, match="steps"):
        ddim.timesteps(s, 0, 0.5)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 999), st.integers(-1, 998), st.integers(0, 2**31 - 1))
def test_ddim_with_exact_v_lands_on_the_true_trajectory(t, t_prev, seed):
    """A perfect v-prediction makes DDIM reproduce x0 and the same noise at any earlier step."""
    s = DDPMSchedule()
    t_prev = min(t_prev, t - 1)
    rng = np.random.default_rng(seed)
    x0, eps = rng.normal(size=(2, 4, 8, 8))
    a, sd = np.sqrt(s.alphas_cumprod[t]), np.sqrt(1 - s.alphas_cumprod[t])
    z_t = a * x0 + sd * eps
    v = a * eps - sd * x0
    got = ddim.step(z_t, v, t, t_prev, s)
    want = x0 if t_prev < 0 else s.add_noise(x0, eps, t_prev)
    assert np.allclose(got, want, atol=1e-8)
