"""The vertex gain network: a per-vertex MLP from `vertex_gain` features to the share of the
networks' correction the vertex follows."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from pipeline.enhance.vertex_gain import GAIN_FEATURES


@dataclass(frozen=True)
class VertexGainConfig:
    """Size and range of the gain network."""

    features: int = GAIN_FEATURES
    hidden: int = 64
    """Width of the two hidden layers."""
    max_gain: float = 2.0
    """Gains lie in (0, max_gain): never against the correction, never far past it."""


class VertexGainNet(nn.Module):
    """(V, F) features -> (V,) gains in (0, max_gain); an untrained net gives about half of it."""

    feature_mean: torch.Tensor
    feature_std: torch.Tensor

    def __init__(self, config: VertexGainConfig) -> None:
        super().__init__()
        self.config = config
        self.register_buffer("feature_mean", torch.zeros(config.features))
        self.register_buffer("feature_std", torch.ones(config.features))
        self.mlp = nn.Sequential(
            nn.Linear(config.features, config.hidden),
            nn.SiLU(),
            nn.Linear(config.hidden, config.hidden),
            nn.SiLU(),
            nn.Linear(config.hidden, 1),
        )

    @staticmethod
    def squash(features: torch.Tensor) -> torch.Tensor:
        """Signed log: steps and spreads span decades between flat parts and creases."""
        return torch.sign(features) * torch.log1p(features.abs())

    def set_normalisation(self, features: torch.Tensor) -> None:
        """Standardises inputs by the mean and std of these (training) features."""
        x = self.squash(features)
        self.feature_mean.copy_(x.mean(0))
        self.feature_std.copy_(x.std(0) + 1e-6)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        x = (self.squash(features) - self.feature_mean) / self.feature_std
        return self.config.max_gain * torch.sigmoid(self.mlp(x)[:, 0])
