"""The latent denoiser: a small U-Net over 4-channel latents with a timestep embedding."""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as nnf
from torch import nn

from pipeline.enhance.models.common import ResBlock, group_norm, timestep_embedding
from pipeline.enhance.models.vae import LATENT_CHANNELS


@dataclass(frozen=True)
class UNetConfig:
    """Size of the latent U-Net (the ControlNet copies its encoder)."""

    channels: tuple[int, ...] = (64, 128)
    """Channels per level; each further level halves the latent resolution."""
    emb_dim: int = 128
    """Width of the timestep embedding."""


class TimeEmbedding(nn.Module):
    def __init__(self, dim: int) -> None:
        super().__init__()
        self.dim = dim
        self.mlp = nn.Sequential(nn.Linear(dim, dim), nn.SiLU(), nn.Linear(dim, dim))

    def forward(self, t: torch.Tensor) -> torch.Tensor:
        return self.mlp(timestep_embedding(t, self.dim))


class UNetEncoder(nn.Module):
    """conv_in, one ResBlock per level with downsampling between, and a middle block.

    Returns the skip features (one per level) and the middle output, which is what ControlNet
    adds its residuals to.
    """

    def __init__(self, config: UNetConfig) -> None:
        super().__init__()
        ch = config.channels
        self.time = TimeEmbedding(config.emb_dim)
        self.conv_in = nn.Conv2d(LATENT_CHANNELS, ch[0], 3, padding=1)
        self.blocks = nn.ModuleList(
            ResBlock(ch[max(i - 1, 0)], c, config.emb_dim) for i, c in enumerate(ch)
        )
        self.downs = nn.ModuleList(nn.Conv2d(c, c, 3, stride=2, padding=1) for c in ch[:-1])
        self.mid = ResBlock(ch[-1], ch[-1], config.emb_dim)

    def forward(
        self, z: torch.Tensor, t: torch.Tensor, hint: torch.Tensor | None = None
    ) -> tuple[list[torch.Tensor], torch.Tensor, torch.Tensor]:
        emb = self.time(t)
        x = self.conv_in(z)
        if hint is not None:
            x = x + hint
        skips = []
        for i, block in enumerate(self.blocks):
            x = block(x, emb)
            skips.append(x)
            if i < len(self.downs):
                x = self.downs[i](x)
        return skips, self.mid(x, emb), emb


class LatentUNet(nn.Module):
    """Predicts v (the DDPM v-parameterisation) from a noisy latent and its timestep."""

    def __init__(self, config: UNetConfig) -> None:
        super().__init__()
        ch = config.channels
        self.encoder = UNetEncoder(config)
        self.ups = nn.ModuleList(
            ResBlock(ch[min(i + 1, len(ch) - 1)] + ch[i], ch[i], config.emb_dim)
            for i in reversed(range(len(ch)))
        )
        self.norm_out = group_norm(ch[0])
        self.conv_out = nn.Conv2d(ch[0], LATENT_CHANNELS, 3, padding=1)

    def forward(
        self,
        z: torch.Tensor,
        t: torch.Tensor,
        control: list[torch.Tensor] | None = None,
    ) -> torch.Tensor:
        """(B, 4, h, w) v-prediction; `control` holds ControlNet residuals (skips..., middle)."""
        skips, x, emb = self.encoder(z, t)
        if control is not None:
            skips = [s + c for s, c in zip(skips, control[:-1], strict=True)]
            x = x + control[-1]
        for block in self.ups:
            skip = skips.pop()
            x = nnf.interpolate(x, size=skip.shape[-2:], mode="nearest")
            x = block(torch.cat([x, skip], dim=1), emb)
        return self.conv_out(nnf.silu(self.norm_out(x)))
