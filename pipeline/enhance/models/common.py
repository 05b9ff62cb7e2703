"""Building blocks shared by the networks, and the depth features every network reads."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as nnf
from torch import nn

SIDE_CHANNELS = 2
"""Side inputs beside the base depth: colour edges (0/1) and the noisy render's depth minus
the base depth (normalised; zero where either is invalid)."""
FEATURE_CHANNELS = 4 + SIDE_CHANNELS
"""mask, high-pass, d/dx, d/dy, then the side inputs."""
DETAIL_SCALE = 100.0
"""Normalised depth is multiplied by this before the network sees differences (1 cm on a
1 m model is about 0.6 after scaling)."""
RESIDUAL_SCALE = 0.01
"""Networks emit corrections in units of this much normalised depth."""


def side_inputs(
    edges: torch.Tensor | None, noisy_n: torch.Tensor, base_n: torch.Tensor, valid: torch.Tensor
) -> torch.Tensor:
    """(B, 2, H, W) side inputs from (B, 1, H, W) colour edges (None: no colour), the noisy
    mesh's render and the base (pre-smoothed) render, valid where the base is."""
    m = valid & (noisy_n < 1.0)
    detail = torch.where(m, noisy_n - base_n, torch.zeros_like(base_n))
    e = edges.to(base_n.dtype) if edges is not None else torch.zeros_like(base_n)
    return torch.cat([e * valid, detail], dim=1)


def depth_features(
    depth_n: torch.Tensor, valid: torch.Tensor, side: torch.Tensor | None = None
) -> torch.Tensor:
    """(B, 6, H, W) shift-invariant features of (B, 1, H, W) normalised depth and its
    (B, 2, H, W) side inputs (`side_inputs`; None: all zero, as for a clean depth).

    Only depth differences enter (high-pass against a masked 5x5 mean, forward differences,
    and the noisy render's offset from the base), scaled and clipped, so a network sees the
    same input whatever the absolute depth; invalid pixels and differences across the
    silhouette are zero.
    """
    m = valid.to(depth_n.dtype)
    d = depth_n * m
    num = nnf.avg_pool2d(d, 5, stride=1, padding=2)
    den = nnf.avg_pool2d(m, 5, stride=1, padding=2).clamp_min(1e-6)
    hp = (d - num / den) * m
    dx = torch.zeros_like(d)
    dy = torch.zeros_like(d)
    dx[..., :, 1:] = (d[..., :, 1:] - d[..., :, :-1]) * m[..., :, 1:] * m[..., :, :-1]
    dy[..., 1:, :] = (d[..., 1:, :] - d[..., :-1, :]) * m[..., 1:, :] * m[..., :-1, :]
    if side is None:
        side = torch.zeros_like(d).expand(-1, SIDE_CHANNELS, -1, -1)
    hp, dx, dy, detail = (
        (f * DETAIL_SCALE).clamp(-3.0, 3.0) for f in (hp, dx, dy, side[:, 1:2] * m)
    )
    return torch.cat([m * 2.0 - 1.0, hp, dx, dy, side[:, 0:1], detail], dim=1)


def group_norm(channels: int) -> nn.GroupNorm:
    return nn.GroupNorm(min(8, channels // 4) or 1, channels)


def timestep_embedding(t: torch.Tensor, dim: int) -> torch.Tensor:
    """(B, dim) sinusoidal embedding of (B,) timesteps, as in the DDPM paper."""
    half = dim // 2
    freqs = torch.exp(-math.log(10000.0) * torch.arange(half, device=t.device) / half)
    args = t.float()[:, None] * freqs[None]
    return torch.cat([torch.cos(args), torch.sin(args)], dim=1)


class ResBlock(nn.Module):
    """GroupNorm-SiLU-conv twice with a skip; optionally shifted by a timestep embedding."""

    def __init__(self, c_in: int, c_out: int, emb_dim: int = 0) -> None:
        super().__init__()
        self.norm1 = group_norm(c_in)
        self.conv1 = nn.Conv2d(c_in, c_out, 3, padding=1)
        self.emb = nn.Linear(emb_dim, c_out) if emb_dim else None
        self.norm2 = group_norm(c_out)
        self.conv2 = nn.Conv2d(c_out, c_out, 3, padding=1)
        self.skip = nn.Conv2d(c_in, c_out, 1) if c_in != c_out else nn.Identity()

    def forward(self, x: torch.Tensor, emb: torch.Tensor | None = None) -> torch.Tensor:
        h = self.conv1(nnf.silu(self.norm1(x)))
        if self.emb is not None and emb is not None:
            h = h + self.emb(nnf.silu(emb))[:, :, None, None]
        h = self.conv2(nnf.silu(self.norm2(h)))
        return self.skip(x) + h


def zero_conv(c_in: int, c_out: int) -> nn.Conv2d:
    """A 1x1 convolution that starts at zero, so a new branch starts as a no-op."""
    conv = nn.Conv2d(c_in, c_out, 1)
    nn.init.zeros_(conv.weight)
    if conv.bias is not None:
        nn.init.zeros_(conv.bias)
    return conv


def pad_to_multiple(x: torch.Tensor, multiple: int) -> tuple[torch.Tensor, tuple[int, int]]:
    """Replicate-pads H and W up to a multiple; returns the original size to crop back."""
    h, w = x.shape[-2:]
    ph, pw = (-h) % multiple, (-w) % multiple
    if ph or pw:
        x = nnf.pad(x, (0, pw, 0, ph), mode="replicate")
    return x, (h, w)


class RowMLP(nn.Module):
    """Two hidden SiLU layers on per-row (per-vertex) features, which are squashed by a signed
    log (they span decades between flat parts and creases) and standardised by the training
    features' statistics (`set_normalisation`)."""

    feature_mean: torch.Tensor
    feature_std: torch.Tensor

    def __init__(self, features: int, hidden: int, outputs: int) -> None:
        super().__init__()
        self.register_buffer("feature_mean", torch.zeros(features))
        self.register_buffer("feature_std", torch.ones(features))
        self.mlp = nn.Sequential(
            nn.Linear(features, hidden),
            nn.SiLU(),
            nn.Linear(hidden, hidden),
            nn.SiLU(),
            nn.Linear(hidden, outputs),
        )

    @staticmethod
    def squash(features: torch.Tensor) -> torch.Tensor:
        return torch.sign(features) * torch.log1p(features.abs())

    def set_normalisation(self, features: torch.Tensor) -> None:
        """Standardises inputs by the mean and std of these (training) features."""
        x = self.squash(features)
        self.feature_mean.copy_(x.mean(0))
        self.feature_std.copy_(x.std(0) + 1e-6)

    def logits(self, features: torch.Tensor) -> torch.Tensor:
        """(B, outputs) the MLP's raw outputs for (B, features) rows."""
        return self.logits_of_squashed(self.squash(features))

    def logits_of_squashed(self, squashed: torch.Tensor) -> torch.Tensor:
        """`logits` of rows already `squash`ed (shared by models reading the same rows)."""
        return self.mlp((squashed - self.feature_mean) / self.feature_std)
