"""The selector: a per-vertex MLP from `twicing_blend` features to blend weights of the
candidate twicings."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import cast

import torch
from torch import nn

from pipeline.enhance.models.common import RowMLP
from pipeline.enhance.presmooth.scale_selection import TwicingBlendConfig


@dataclass(frozen=True)
class SelectorConfig:
    """The candidates and features it was trained on (`TwicingBlendConfig`), and its size."""

    iterations: tuple[int, ...] = TwicingBlendConfig.iterations
    pilot_iterations: int = TwicingBlendConfig.pilot_iterations
    passes: int = TwicingBlendConfig.passes
    feature_rings: tuple[int, ...] = TwicingBlendConfig.feature_rings
    boundary_pilot_iterations: int = TwicingBlendConfig.boundary_pilot_iterations
    """Pilot count along open boundaries; weights whose metadata lacks it load with the
    default."""
    hidden: int = 64
    """Width of the two hidden layers."""

    @property
    def blend(self) -> TwicingBlendConfig:
        return TwicingBlendConfig(self.iterations, self.pilot_iterations, self.passes,
                                  self.feature_rings, self.boundary_pilot_iterations)


class TwicingSelector(RowMLP):
    """(V, F) features -> (V, K) convex weights over the K candidates."""

    def __init__(self, config: SelectorConfig) -> None:
        super().__init__(config.blend.feature_count, config.hidden, len(config.iterations))
        self.config = config

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return self.weights_of_squashed(self.squash(features))

    def weights_of_squashed(self, squashed: torch.Tensor) -> torch.Tensor:
        """The weights of rows already `squash`ed."""
        return torch.softmax(self.logits_of_squashed(squashed), dim=1)


class SelectorEnsemble(nn.Module):
    """Selectors trained alike from different seeds on the same candidates and features:
    (V, F) features -> the mean of their (V, K) weights, convex as each member's is."""

    def __init__(self, members: Sequence[TwicingSelector]) -> None:
        super().__init__()
        if not members:
            raise ValueError("--selector-ensemble: no members")
        if len({m.config.blend for m in members}) != 1:
            raise ValueError("--selector-ensemble: its members weigh different candidates")
        self.members = nn.ModuleList(members)
        self.config = members[0].config

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        # The rows are squashed once for all members, not once per member.
        squashed = RowMLP.squash(features)
        members = cast(Sequence[TwicingSelector], self.members)
        return torch.stack([m.weights_of_squashed(squashed) for m in members]).mean(dim=0)
