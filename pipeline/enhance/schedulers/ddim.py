"""DDIM sampling maths (deterministic, eta = 0) for v-prediction networks."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from pipeline.enhance.schedulers.ddpm import DDPMSchedule


def timesteps(schedule: DDPMSchedule, steps: int, strength: float) -> NDArray[np.int64]:
    """Descending timesteps of a `steps`-step run that starts `strength` of the way into the
    noise (strength 1 = pure noise, as in img2img)."""
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    if not 0.0 < strength <= 1.0:
        raise ValueError(f"strength must be in (0, 1], got {strength}")
    t_start = max(int(round(strength * schedule.num_train_steps)) - 1, 0)
    ts = np.linspace(t_start, 0, steps + 1)[:-1] if steps > 1 else np.array([t_start])
    return np.unique(np.round(ts).astype(np.int64))[::-1].copy()


def split_v(z_t, v, alpha_bar: float):
    """(x0, eps) from a noisy sample and its v-prediction: x0 = a z - s v, eps = s z + a v."""
    a, s = np.sqrt(alpha_bar), np.sqrt(1.0 - alpha_bar)
    return a * z_t - s * v, s * z_t + a * v


def step(z_t, v, t: int, t_prev: int, schedule: DDPMSchedule):
    """One DDIM update from t to t_prev (t_prev < 0 returns the clean estimate)."""
    x0, eps = split_v(z_t, v, float(schedule.alphas_cumprod[t]))
    if t_prev < 0:
        return x0
    a_prev = float(schedule.alphas_cumprod[t_prev])
    return np.sqrt(a_prev) * x0 + np.sqrt(1.0 - a_prev) * eps
