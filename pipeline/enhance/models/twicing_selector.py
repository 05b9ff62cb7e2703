"""The selector: a per-vertex MLP from `twicing_blend` features to blend weights of the
candidate twicings."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from pipeline.enhance.twicing_blend import TwicingBlendConfig


@dataclass(frozen=True)
class SelectorConfig:
    """The candidates and features it was trained on (`TwicingBlendConfig`), and its size."""

    iterations: tuple[int, ...] = TwicingBlendConfig.iterations
    pilot_iterations: int = TwicingBlendConfig.pilot_iterations
    passes: int = TwicingBlendConfig.passes
    feature_rings: tuple[int, ...] = TwicingBlendConfig.feature_rings
    hidden: int = 64
    """Width of the two hidden layers."""

    @property
    def blend(self) -> TwicingBlendConfig:
        return TwicingBlendConfig(self.iterations, self.pilot_iterations, self.passes,
                                  self.feature_rings)


class TwicingSelector(nn.Module):
    """(V, F) features -> (V, K) convex weights over the K candidates."""

    feature_mean: torch.Tensor
    feature_std: torch.Tensor

    def __init__(self, config: SelectorConfig) -> None:
        super().__init__()
        self.config = config
        features = config.blend.feature_count
        self.register_buffer("feature_mean", torch.zeros(features))
        self.register_buffer("feature_std", torch.ones(features))
        self.mlp = nn.Sequential(
            nn.Linear(features, config.hidden),
            nn.SiLU(),
            nn.Linear(config.hidden, config.hidden),
            nn.SiLU(),
            nn.Linear(config.hidden, len(config.iterations)),
        )

    @staticmethod
    def squash(features: torch.Tensor) -> torch.Tensor:
        """Signed log: squared residuals span decades between flat parts and creases."""
        return torch.sign(features) * torch.log1p(features.abs())

    def set_normalisation(self, features: torch.Tensor) -> None:
        """Standardises inputs by the mean and std of these (training) features."""
        x = self.squash(features)
        self.feature_mean.copy_(x.mean(0))
        self.feature_std.copy_(x.std(0) + 1e-6)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        x = (self.squash(features) - self.feature_mean) / self.feature_std
        return torch.softmax(self.mlp(x), dim=1)
