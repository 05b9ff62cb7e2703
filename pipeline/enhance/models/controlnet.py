"""ControlNet: a trainable copy of the U-Net encoder that reads the base depth and its side
inputs (colour edges, the noisy render's detail) and adds its features to the U-Net's through
zero-initialised convolutions."""

from __future__ import annotations

import torch
import torch.nn.functional as nnf
from torch import nn

from pipeline.enhance.models.common import FEATURE_CHANNELS, depth_features, zero_conv
from pipeline.enhance.models.unet import LatentUNet, UNetConfig, UNetEncoder


class HintEncoder(nn.Module):
    """Full-resolution depth features down to the latent's 1/8 grid, ending in a zero conv."""

    def __init__(self, out_channels: int) -> None:
        super().__init__()
        widths = (16, 32, 64)
        layers: list[nn.Module] = [nn.Conv2d(FEATURE_CHANNELS, widths[0], 3, padding=1)]
        for c_in, c_out in zip(widths, (*widths[1:], widths[-1]), strict=True):
            layers += [nn.SiLU(), nn.Conv2d(c_in, c_out, 3, stride=2, padding=1)]
        layers += [nn.SiLU()]
        self.body = nn.Sequential(*layers)
        self.out = zero_conv(widths[-1], out_channels)

    def forward(self, feats: torch.Tensor) -> torch.Tensor:
        return self.out(self.body(feats))


class ControlNet(nn.Module):
    """Produces one residual per U-Net skip plus one for the middle block."""

    def __init__(self, config: UNetConfig) -> None:
        super().__init__()
        self.hint = HintEncoder(config.channels[0])
        self.encoder = UNetEncoder(config)
        self.zero_skips = nn.ModuleList(zero_conv(c, c) for c in config.channels)
        self.zero_mid = zero_conv(config.channels[-1], config.channels[-1])

    def copy_encoder_from(self, unet: LatentUNet) -> None:
        """Starts the branch as a copy of the U-Net's encoder, as ControlNet does."""
        self.encoder.load_state_dict(unet.encoder.state_dict())

    def hint_of(
        self,
        degraded_n: torch.Tensor,
        degraded_valid: torch.Tensor,
        side: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """The conditioning on the latent grid; it depends on neither noise nor timestep, so a
        sampler computes it once."""
        return self.hint(depth_features(degraded_n, degraded_valid, side))

    def forward(self, z: torch.Tensor, t: torch.Tensor, hint: torch.Tensor) -> list[torch.Tensor]:
        """Residuals for the U-Net's skips and middle block from a noisy latent and the hint."""
        if hint.shape[-2:] != z.shape[-2:]:
            hint = nnf.interpolate(hint, size=z.shape[-2:], mode="nearest")
        skips, mid, _ = self.encoder(z, t, hint)
        return [zc(s) for zc, s in zip(self.zero_skips, skips, strict=True)] + [self.zero_mid(mid)]
