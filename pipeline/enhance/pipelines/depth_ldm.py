"""Latent-diffusion depth enhancement: encode the degraded depth, noise it part-way (strength),
denoise with a few DDIM steps under ControlNet guidance, decode guided by the degraded depth.

With a `refines` regressor the degraded depth is first replaced by the regressor's estimate, and
the diffusion model learns what is left (the split of CorrDiff, Mardani et al. 2023: a
regression for the mean, the generative model for the residual). A decoder guided by the base
depth alone has to relearn everything the regressor knows before it can add to it.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from pipeline.enhance.models.controlnet import ControlNet
from pipeline.enhance.models.regressor import ResidualUNet
from pipeline.enhance.models.unet import LatentUNet
from pipeline.enhance.models.vae import LATENT_CHANNELS, DepthVAE, padded
from pipeline.enhance.schedulers import ddim
from pipeline.enhance.schedulers.ddpm import DDPMSchedule


@dataclass(frozen=True)
class LDMModels:
    """The three trained parts of the latent diffusion enhancer."""

    vae: DepthVAE
    """Autoencoder (its decoder is guided by the degraded depth)."""
    unet: LatentUNet
    """Latent denoiser (v-prediction)."""
    controlnet: ControlNet
    """Conditioning branch on the base depth and its side inputs (colour edges, noisy detail)."""
    refines: ResidualUNet | None = None
    """A trained, frozen regressor whose estimate stands in for the base depth everywhere
    below (encoding, hint, decoder guide); None: the LDM corrects the base depth itself."""


def sample_depth(
    models: LDMModels,
    depth_n: torch.Tensor,
    valid: torch.Tensor,
    steps: int,
    strength: float,
    noise: torch.Tensor,
    side: torch.Tensor | None = None,
) -> torch.Tensor:
    """(B, 1, H, W) enhanced depth: the whole sampler, differentiable, so end-to-end
    fine-tuning trains exactly what inference runs.

    `noise` is the (B, 4, H/8, W/8) start noise for the padded size (`latent_shape`).
    """
    schedule = DDPMSchedule()
    depth_n = guide_depth(models.refines, depth_n, valid, side)
    d, v, (h, w) = padded(depth_n, valid)
    side_p = None if side is None else padded(side, valid)[0]
    scale = models.vae.latent_scale
    z_start = models.vae.encode(d, v).mean * scale
    hint = models.controlnet.hint_of(d, v, side_p)
    ts = ddim.timesteps(schedule, steps, strength)
    a0 = float(schedule.alphas_cumprod[ts[0]])
    z = a0**0.5 * z_start + (1.0 - a0) ** 0.5 * noise
    for i, t in enumerate(ts):
        t_batch = torch.full((z.shape[0],), int(t), device=z.device, dtype=torch.long)
        v_pred = models.unet(z, t_batch, models.controlnet(z, t_batch, hint))
        t_prev = int(ts[i + 1]) if i + 1 < len(ts) else -1
        z = ddim.step(z, v_pred, int(t), t_prev, schedule)
    out = models.vae.decode(z / scale, d, v, side_p)
    return out[..., :h, :w]


def guide_depth(
    refines: ResidualUNet | None,
    depth_n: torch.Tensor,
    valid: torch.Tensor,
    side: torch.Tensor | None,
) -> torch.Tensor:
    """(B, 1, H, W) the depth the LDM corrects: the regressor's estimate from the base depth,
    or the base depth itself. The side inputs stay those of the base (the noisy render's offset
    from it), so both networks read the same evidence."""
    if refines is None:
        return depth_n
    with torch.no_grad():
        return refines(depth_n, valid, side)


def latent_shape(depth_n: torch.Tensor) -> tuple[int, int, int, int]:
    """(B, 4, H/8, W/8) of the latent of (B, 1, H, W) depth after padding to multiples of 8."""
    b, _, h, w = depth_n.shape
    return (b, LATENT_CHANNELS, (h + 7) // 8, (w + 7) // 8)


@torch.no_grad()
def enhance_depth_ldm(
    models: LDMModels,
    depth_n: torch.Tensor,
    valid: torch.Tensor,
    steps: int,
    strength: float,
    seed: int,
    side: torch.Tensor | None = None,
) -> torch.Tensor:
    """(B, 1, H, W) enhanced normalised depth from (B, 1, H, W) degraded depth and mask.

    Deterministic for a seed: the start noise comes from a generator seeded with it and DDIM
    adds none (eta = 0). One step predicts the clean latent straight from the start.
    """
    gen = torch.Generator(device="cpu").manual_seed(seed)
    noise = torch.randn(latent_shape(depth_n), generator=gen).to(depth_n.device)
    return sample_depth(models, depth_n, valid, steps, strength, noise, side)
