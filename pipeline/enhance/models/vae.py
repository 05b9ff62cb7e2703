"""KL-regularised autoencoder: depth -> 4-channel latent at 1/8 resolution -> depth.

A latent at 1/8 cannot hold millimetre detail of a 256² depth image, so the decoder is guided by
features of the degraded depth at every scale (as StableSR's feature wrapping does) and emits a
correction to the degraded depth; the latent carries what the degraded image does not show.
"""

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

LATENT_CHANNELS = 4


@dataclass(frozen=True)
class VAEConfig:
    """Size of the autoencoder."""

    channels: tuple[int, int, int, int] = (16, 32, 64, 64)
    """Channels at 1, 1/2, 1/4 and 1/8 resolution."""
    initial_logvar: float = -6.0
    """Starting log-variance of the posterior. Starting at the prior's 0 makes early latents
    pure noise, and a decoder that also sees the degraded depth learns to ignore them for good
    (posterior collapse); a small start keeps the latent informative from the first step."""


class DiagonalGaussian:
    """The encoder's posterior N(mean, exp(logvar)) per latent element."""

    def __init__(self, moments: torch.Tensor) -> None:
        self.mean, logvar = moments.chunk(2, dim=1)
        self.logvar = logvar.clamp(-30.0, 20.0)

    def sample(self) -> torch.Tensor:
        return self.mean + torch.exp(0.5 * self.logvar) * torch.randn_like(self.mean)

    def kl(self) -> torch.Tensor:
        """(B,) KL divergence to the standard normal, summed over elements."""
        return 0.5 * torch.sum(self.mean**2 + self.logvar.exp() - 1.0 - self.logvar, dim=(1, 2, 3))


class _Pyramid(nn.Module):
    """Depth features at 1, 1/2, 1/4, 1/8 resolution."""

    def __init__(self, ch: tuple[int, int, int, int], in_channels: int = FEATURE_CHANNELS
                 ) -> None:
        super().__init__()
        self.conv_in = nn.Conv2d(in_channels, ch[0], 3, padding=1)
        self.blocks = nn.ModuleList(ResBlock(ch[max(i - 1, 0)], ch[i]) for i in range(4))
        self.downs = nn.ModuleList(
            nn.Conv2d(ch[i], ch[i], 3, stride=2, padding=1) for i in range(3)
        )

    def forward(self, feats: torch.Tensor) -> list[torch.Tensor]:
        x = self.conv_in(feats)
        out = []
        for i, block in enumerate(self.blocks):
            x = block(x)
            out.append(x)
            if i < 3:
                x = self.downs[i](x)
        return out


class DepthVAE(nn.Module):
    """Encoder, posterior and depth-guided decoder."""

    def __init__(self, config: VAEConfig) -> None:
        super().__init__()
        ch = config.channels
        self.encoder = _Pyramid(ch)
        self.to_moments = nn.Conv2d(ch[3], 2 * LATENT_CHANNELS, 3, padding=1)
        if self.to_moments.bias is not None:
            with torch.no_grad():
                self.to_moments.bias[LATENT_CHANNELS:].fill_(config.initial_logvar)
        self.guide = _Pyramid(ch)
        self.from_latent = nn.Conv2d(LATENT_CHANNELS, ch[3], 3, padding=1)
        self.up_blocks = nn.ModuleList(
            [ResBlock(2 * ch[3], ch[3])]
            + [ResBlock(ch[i + 1] + ch[i], ch[i]) for i in reversed(range(3))]
        )
        self.conv_out = nn.Conv2d(ch[0], 1, 3, padding=1)
        self.register_buffer("latent_scale", torch.ones(()))
        self.latent_scale: torch.Tensor

    def encode(self, depth_n: torch.Tensor, valid: torch.Tensor) -> DiagonalGaussian:
        """Posterior over the (B, 4, H/8, W/8) latent of (B, 1, H, W) depth; H, W divisible by
        8. Its features are local and shift-invariant: the latent holds the shape's detail,
        the guide of the decoder its place."""
        return DiagonalGaussian(self.to_moments(self.encoder(depth_features(depth_n, valid))[-1]))

    def decode(
        self,
        latent: torch.Tensor,
        guide_depth_n: torch.Tensor,
        guide_valid: torch.Tensor,
        side: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """(B, 1, H, W) depth from a latent, guided by the degraded depth it should correct."""
        g = self.guide(depth_features(guide_depth_n, guide_valid, side))
        x = self.up_blocks[0](torch.cat([self.from_latent(latent), g[3]], dim=1))
        for level, block in zip((2, 1, 0), self.up_blocks[1:], strict=True):
            x = nnf.interpolate(x, size=g[level].shape[-2:], mode="nearest")
            x = block(torch.cat([x, g[level]], dim=1))
        return guide_depth_n + self.conv_out(x) * RESIDUAL_SCALE


def padded(depth_n: torch.Tensor, valid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, tuple]:
    """Pads depth and mask to multiples of 8 (replicated depth, invalid mask)."""
    d, size = pad_to_multiple(depth_n, 8)
    v, _ = pad_to_multiple(valid.float(), 8)
    return d, v > 0.5, size
