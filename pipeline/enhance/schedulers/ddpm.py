"""The DDPM training schedule: betas and cumulative alphas (numpy, no networks)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class DDPMSchedule:
    """A "scaled linear" beta schedule, as Stable Diffusion trains with."""

    num_train_steps: int = 1000
    """Diffusion steps T."""
    beta_start: float = 0.00085
    """Beta at t = 0."""
    beta_end: float = 0.012
    """Beta at t = T - 1."""
    alphas_cumprod: NDArray[np.float64] = field(init=False, repr=False)
    """(T,) cumulative product of (1 - beta)."""

    def __post_init__(self) -> None:
        if self.num_train_steps < 2:
            raise ValueError(f"num_train_steps must be >= 2, got {self.num_train_steps}")
        betas = np.linspace(self.beta_start**0.5, self.beta_end**0.5, self.num_train_steps) ** 2
        object.__setattr__(self, "alphas_cumprod", np.cumprod(1.0 - betas))

    def add_noise(self, x0: NDArray, noise: NDArray, t: int) -> NDArray:
        """x_t = sqrt(abar_t) x0 + sqrt(1 - abar_t) noise."""
        a = self.alphas_cumprod[t]
        return np.sqrt(a) * x0 + np.sqrt(1.0 - a) * noise
