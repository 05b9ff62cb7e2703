"""The plain baseline: a residual U-Net from degraded depth features to a depth correction."""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as nnf
from torch import nn

from pipeline.enhance.models.common import (
    FEATURE_CHANNELS,
    RESIDUAL_SCALE,
    ResBlock,
    depth_features,
    pad_to_multiple,
)


@dataclass(frozen=True)
class RegressorConfig:
    """Size of the residual U-Net."""

    channels: tuple[int, ...] = (16, 32, 64, 128)
    """Channels per level, full resolution first; each further level halves the resolution."""


class ResidualUNet(nn.Module):
    """Predicts clean depth = degraded depth + correction, fully convolutional."""

    def __init__(self, config: RegressorConfig) -> None:
        super().__init__()
        self.config = config
        ch = config.channels
        self.conv_in = nn.Conv2d(FEATURE_CHANNELS, ch[0], 3, padding=1)
        self.down = nn.ModuleList()
        self.pool = nn.ModuleList()
        for i, c in enumerate(ch):
            self.down.append(ResBlock(ch[max(i - 1, 0)] if i else ch[0], c))
            if i < len(ch) - 1:
                self.pool.append(nn.Conv2d(c, c, 3, stride=2, padding=1))
        self.mid = ResBlock(ch[-1], ch[-1])
        self.up = nn.ModuleList(
            ResBlock(ch[i + 1] + ch[i], ch[i]) for i in reversed(range(len(ch) - 1))
        )
        self.conv_out = nn.Conv2d(ch[0], 1, 3, padding=1)
        self.levels = len(ch)

    def forward(
        self, depth_n: torch.Tensor, valid: torch.Tensor, side: torch.Tensor | None = None
    ) -> torch.Tensor:
        """(B, 1, H, W) enhanced normalised depth from degraded depth and its validity mask."""
        x, (h, w) = pad_to_multiple(depth_features(depth_n, valid, side), 2 ** (self.levels - 1))
        x = self.conv_in(x)
        skips = []
        for i, block in enumerate(self.down):
            x = block(x)
            if i < self.levels - 1:
                skips.append(x)
                x = self.pool[i](x)
        x = self.mid(x)
        for block in self.up:
            skip = skips.pop()
            x = nnf.interpolate(x, size=skip.shape[-2:], mode="nearest")
            x = block(torch.cat([x, skip], dim=1))
        correction = self.conv_out(x)[..., :h, :w] * RESIDUAL_SCALE
        return depth_n + correction

