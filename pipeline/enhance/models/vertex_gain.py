"""The vertex gain network: a per-vertex MLP from `vertex_gain` features to the share of the
networks' correction the vertex follows."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from pipeline.enhance.models.common import RowMLP
from pipeline.enhance.update.vertex_gain import GAIN_FEATURES


@dataclass(frozen=True)
class VertexGainConfig:
    """Size and range of the gain network."""

    features: int = GAIN_FEATURES
    hidden: int = 64
    """Width of the two hidden layers."""
    max_gain: float = 2.0
    """Gains lie in (0, max_gain): never against the correction, never far past it."""


class VertexGainNet(RowMLP):
    """(V, F) features -> (V,) gains in (0, max_gain); an untrained net gives about half of it."""

    def __init__(self, config: VertexGainConfig) -> None:
        super().__init__(config.features, config.hidden, 1)
        self.config = config

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return self.config.max_gain * torch.sigmoid(self.logits(features)[:, 0])
