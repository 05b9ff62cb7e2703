"""Training loops: the residual regressor, the VAE, the latent U-Net with its ControlNet, then
end-to-end fine-tuning of all three through the few-step sampler.

Loops are time- and step-bounded, seeded, and resumable: every `checkpoint_every` steps they hand
a state dict to a callback (the CLI writes it) and accept one back to continue.
"""

from __future__ import annotations

import io
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import torch
import torch.nn.functional as nnf
from torch import nn

from pipeline.enhance.data import SAME_SURFACE_N, DataConfig, DepthPairs, same_surface_mask
from pipeline.enhance.models.common import RESIDUAL_SCALE, side_inputs
from pipeline.enhance.models.controlnet import ControlNet
from pipeline.enhance.models.regressor import RegressorConfig, ResidualUNet
from pipeline.enhance.models.unet import LatentUNet, UNetConfig
from pipeline.enhance.models.vae import DepthVAE, VAEConfig
from pipeline.enhance.pipelines.depth_ldm import (
    LDMModels,
    guide_depth,
    latent_shape,
    sample_depth,
)
from pipeline.enhance.schedulers.ddpm import DDPMSchedule
from pipeline.enhance.selector_training import SelectorConfig, SelectorTrainConfig

Checkpoint = dict[str, Any]


@dataclass(frozen=True)
class StageBudget:
    """Limits of one training stage."""

    steps: int
    """Most optimiser steps."""
    minutes: float
    """Most wall-clock minutes (counted across resumes)."""
    lr: float = 1e-3
    """AdamW learning rate (cosine-decayed over `steps`)."""


@dataclass(frozen=True)
class TrainConfig:
    """A whole training run."""

    name: str
    """Configuration name (tiny, small, large)."""
    data: DataConfig = field(default_factory=DataConfig)
    """Training-pair generation."""
    selector: SelectorTrainConfig = field(default_factory=SelectorTrainConfig)
    """The twicing selector's data and budget (its own stage; no depth pairs)."""
    regressor: RegressorConfig = field(default_factory=RegressorConfig)
    """Baseline network size."""
    vae: VAEConfig = field(default_factory=VAEConfig)
    """Autoencoder size."""
    unet: UNetConfig = field(default_factory=UNetConfig)
    """Latent U-Net (and ControlNet copy) size."""
    crop: int = 96
    """Training crop side in pixels (a multiple of 8)."""
    batch: int = 16
    """Crops per step."""
    regressor_budget: StageBudget = StageBudget(3000, 15.0)
    """Regressor stage limits."""
    vae_budget: StageBudget = StageBudget(3000, 12.0)
    """VAE stage limits."""
    ldm_budget: StageBudget = StageBudget(6000, 25.0, 5e-4)
    """U-Net + ControlNet stage limits."""
    finetune_budget: StageBudget = StageBudget(6000, 25.0, 2e-4)
    """End-to-end fine-tuning limits."""
    finetune_steps: tuple[int, ...] = (1, 2, 4)
    """DDIM step counts the fine-tuning unrolls (one drawn per batch), so each sampling mode
    up to the default 4 is trained."""
    finetune_strength: float = 0.5
    """Sampling strength during fine-tuning (the enhance stage's default)."""
    checkpoint_every: int = 100
    """Steps between checkpoints."""
    kl_weight: float = 1e-3
    """Weight of the VAE's KL term, per pixel (KL summed over the latent, divided by the
    image's pixels). Against the summed KL, as first written, the weight was some 16 000 times
    what the mean per-pixel loss can carry: the posterior collapsed and the decoder, which
    also sees the degraded depth, learnt to ignore the latent (clean and degraded latents
    decoded alike)."""
    kl_warmup_fraction: float = 0.5
    """The KL weight ramps up from 0 over this fraction of the VAE's steps (against collapse)."""
    ldm_max_timestep: int = 600
    """Training timesteps are drawn below this: sampling starts part-way (strength <= 0.6),
    so capacity is not spent on the pure-noise end of the schedule."""
    validation_views: int = 24
    """Validation images scored at the end of each stage."""
    loss_slope_power: int = 0
    """The regressor's and the end-to-end stage's depth loss weighs each pixel by cos^p of the
    clean surface's slant to the view (`slope_weights`); 0: plain depth MSE. The mesh update
    moves a vertex along each view's ray by its depth change, weighted by cos², so a depth
    error e moves the surface by e·cos along its normal and p = 4 is the error the mesh sees
    (`depth_scores`' normal RMSE). Plain MSE is dominated by grazing pixels, and on vertex
    noise alone, in the update's weighting, the shipped regressor and LDM are worse than the
    pre-smoothed base they correct (0.608 and 0.588 against 0.583 per mille) while their
    plain depth error is lower (1.10 and 1.08 against 1.12). But p = 4 did not help: the LDM
    fine-tuned with it (the shipped LDM's recipe, same pairs and budget) gave 0.592 there and
    spot 0.777 / fandisk 0.729 mm on meshes, against 0.775 / 0.727 with p = 0. So it is 0."""
    loss_mask_threshold_n: float = SAME_SURFACE_N
    """Pixels where an input is further than this (normalised depth) from the clean render
    are left out of the losses (`same_surface_mask`): another surface is seen there. The
    default, 0.05, is what the earlier weights were trained with; `BULK_SURFACE_N` (0.02),
    which the shipped weights were last trained with (`--loss-mask 0.02`), leaves out the rest
    of those pixels, which at 0.05 still carried about 40 % of the squared loss."""
    ldm_refines_regressor: bool = True
    """The VAE, LDM and fine-tuning stages train on the regressor's estimate in place of the
    base depth (`LDMModels.refines`), so the LDM learns what the regressor leaves; their
    stages then need a trained regressor."""


CONFIGS: dict[str, TrainConfig] = {
    "tiny": TrainConfig(
        name="tiny",
        data=DataConfig(
            resolution=64, poses_per_mesh=1, views_per_pose=2, edge_fraction=(0.02, 0.03)
        ),
        selector=SelectorTrainConfig(
            model=SelectorConfig(hidden=8), draws_per_mesh=1, edge_fraction=(0.03, 0.04),
            vertices_per_draw=2000, steps=5, batch=256,
        ),
        regressor=RegressorConfig(channels=(8, 16)),
        vae=VAEConfig(channels=(8, 8, 16, 16)),
        unet=UNetConfig(channels=(16, 16), emb_dim=32),
        crop=32,
        batch=2,
        regressor_budget=StageBudget(3, 1.0),
        vae_budget=StageBudget(3, 1.0),
        ldm_budget=StageBudget(3, 1.0),
        finetune_budget=StageBudget(3, 1.0),
        checkpoint_every=2,
        validation_views=2,
    ),
    # About 52 minutes of optimisation on 2 CPU cores, most of it end-to-end; with data and
    # validation the whole run stays within an hour.
    "small": TrainConfig(
        name="small",
        data=DataConfig(poses_per_mesh=12),
        crop=128,
        batch=8,
        regressor_budget=StageBudget(6000, 11.0),
        vae_budget=StageBudget(3000, 8.0),
        ldm_budget=StageBudget(3000, 8.0, 5e-4),
        finetune_budget=StageBudget(6000, 25.0, 2e-4),
    ),
    # The shipped weights' recipe, run on one H100 (2026-11-24) with `--procedural 12
    # --workers 14`: the small networks with 4x the batch and 2.7x the poses. There the
    # stages took 3.0 / 1.7 / 1.7 / 5.8 minutes (and the pairs 2 minutes); on 2 CPU cores
    # they would take about a day. Since then its pairs are pre-smoothed by the shipped
    # selector (`presmooth_learned`), as the enhance stage now does, and its selector stage
    # is the shipped selector's recipe (13 minutes on 2 CPU cores).
    "large": TrainConfig(
        name="large",
        selector=SelectorTrainConfig(model=SelectorConfig(hidden=128), draws_per_mesh=6,
                                     vertices_per_draw=60_000, steps=12000, minutes=30.0),
        data=DataConfig(poses_per_mesh=32),
        crop=128,
        batch=32,
        regressor_budget=StageBudget(11583, 30.0),
        vae_budget=StageBudget(3929, 20.0),
        ldm_budget=StageBudget(3781, 20.0, 5e-4),
        finetune_budget=StageBudget(4716, 40.0, 2e-4),
        checkpoint_every=500,
        validation_views=96,
    ),
}


def _each_budget(config: TrainConfig, change: Callable[[StageBudget], StageBudget]) -> TrainConfig:
    """`config` with `change` applied to every network stage's budget (the selector has its
    own config)."""
    return replace(
        config,
        regressor_budget=change(config.regressor_budget),
        vae_budget=change(config.vae_budget),
        ldm_budget=change(config.ldm_budget),
        finetune_budget=change(config.finetune_budget),
    )


def scaled(config: TrainConfig, factor: float) -> TrainConfig:
    """The same configuration with every stage's step and time budget multiplied by `factor`."""
    if factor <= 0:
        raise ValueError(f"budget scale must be > 0, got {factor}")
    selector = replace(config.selector, steps=max(1, int(config.selector.steps * factor)),
                       minutes=config.selector.minutes * factor)
    return _each_budget(
        replace(config, selector=selector),
        lambda b: replace(b, steps=max(1, int(b.steps * factor)), minutes=b.minutes * factor),
    )


def capped(config: TrainConfig, minutes: float) -> TrainConfig:
    """The same configuration with every network stage's wall-clock limit set to `minutes`
    (steps unchanged, so the learning-rate schedule is the step budget's)."""
    return _each_budget(config, lambda b: replace(b, minutes=minutes))


def with_lr(config: TrainConfig, lr: float) -> TrainConfig:
    """The same configuration with every network stage's peak learning rate set to `lr`."""
    return _each_budget(config, lambda b: replace(b, lr=lr))


class CropSampler:
    """Random crops of the pairs with random flips and transposes, mostly on the surface.

    The images live as one (6, N, H, W) float tensor on the device of the first batch and
    crops are gathered for a whole batch at once: on a GPU a crop-by-crop Python loop took
    as long as the training step it fed.
    """

    def __init__(
        self, pairs: DepthPairs, crop: int, seed: int, mask_threshold_n: float = SAME_SURFACE_N
    ) -> None:
        mask = same_surface_mask(pairs, threshold_n=mask_threshold_n)
        self.images = torch.from_numpy(np.stack([
            pairs.degraded_n, pairs.degraded_valid, pairs.clean_n, mask, pairs.edges,
            pairs.noisy_n,
        ]).astype(np.float32))
        self.crop = min(crop, pairs.degraded_n.shape[-1])
        self.resolution = pairs.degraded_n.shape[-1]
        """Side of the full images in pixels (crops keep their pixel size)."""
        self.rng = np.random.default_rng(seed)

    def batch(self, size: int, device: torch.device) -> tuple[torch.Tensor, ...]:
        """(base depth, its validity, clean depth, loss mask), each (size, 1, crop, crop), and
        the (size, 2, crop, crop) side inputs (`side_inputs`)."""
        self.images = self.images.to(device)
        i, y, x = self._origins(size, device)
        c = self.crop
        span = torch.arange(c, device=device)
        p, q = span[:, None].expand(c, c), span[None, :].expand(c, c)
        # A flip or transpose of a crop is a reordering of the pixels it gathers.
        flip_x, flip_y, swap = (
            torch.from_numpy(self.rng.random(size) < 0.5).to(device)[:, None, None]
            for _ in range(3)
        )
        u, v = torch.where(swap, q, p), torch.where(swap, p, q)
        rows = y[:, None, None] + torch.where(flip_y, c - 1 - u, u)
        cols = x[:, None, None] + torch.where(flip_x, c - 1 - v, v)
        crops = self.images[:, i[:, None, None], rows, cols].transpose(0, 1)  # (size, 6, c, c)
        deg, valid, clean, mask, edges, noisy = crops.split(1, dim=1)
        valid, mask = valid > 0.5, mask > 0.5
        return deg, valid, clean, mask, side_inputs(edges, noisy, deg, valid)

    def _origins(self, size: int, device: torch.device) -> tuple[torch.Tensor, ...]:
        """(size,) image indices and crop corners whose crops are at least 20 % loss mask."""
        _, n, h, w = self.images.shape
        c = self.crop
        span = torch.arange(c, device=device)
        found: list[torch.Tensor] = []
        while sum(len(f) for f in found) < size:
            draw = torch.from_numpy(np.stack([
                self.rng.integers(n, size=2 * size),
                self.rng.integers(h - c + 1, size=2 * size),
                self.rng.integers(w - c + 1, size=2 * size),
            ], axis=1)).to(device)
            i, y, x = draw.unbind(1)
            mask = self.images[3, i[:, None, None], (y[:, None] + span)[:, :, None],
                               (x[:, None] + span)[:, None, :]]
            found.append(draw[mask.mean(dim=(1, 2)) >= 0.2])
        return torch.cat(found)[:size].unbind(1)


def masked_mse(
    pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor, weight: torch.Tensor | None = None
) -> torch.Tensor:
    """Mean squared error over the mask (weighted by `weight` when given), in units of
    RESIDUAL_SCALE."""
    m = mask.to(pred.dtype) if weight is None else mask.to(pred.dtype) * weight
    err = (pred - target) / RESIDUAL_SCALE
    return (err**2 * m).sum() / m.sum().clamp_min(1e-6)


def loss_weights(clean_n: torch.Tensor, resolution: int, power: int) -> torch.Tensor | None:
    """The depth loss's pixel weights (`TrainConfig.loss_slope_power`); None (plain MSE, no
    work on the training step) for power 0."""
    return None if power == 0 else slope_weights(clean_n, resolution, power)


def slope_weights(clean_n: torch.Tensor, resolution: int, power: int) -> torch.Tensor:
    """(B, 1, H, W) cos^power of the slant of the (B, 1, H, W) clean surface to the view:
    cos = 1 / sqrt(1 + |grad z|²) with the slope from central differences of the orthographic
    render, whose normalised depth unit is the image side (`resolution` pixels)."""
    c = nnf.pad(clean_n, (1, 1, 1, 1), mode="replicate")
    gx = (c[..., 1:-1, 2:] - c[..., 1:-1, :-2]) * (0.5 * resolution)
    gy = (c[..., 2:, 1:-1] - c[..., :-2, 1:-1]) * (0.5 * resolution)
    return (1.0 + gx**2 + gy**2) ** (-0.5 * power)


def resolve_device(name: str) -> torch.device:
    """'auto' (CUDA when present, else CPU), 'cpu' or 'cuda'."""
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name not in ("cpu", "cuda"):
        raise ValueError(f"device: {name!r} is not one of auto, cpu, cuda")
    if name == "cuda" and not torch.cuda.is_available():
        raise ValueError("device: cuda requested but no CUDA device is available")
    return torch.device(name)


def checkpoint_to_bytes(checkpoint: Checkpoint) -> bytes:
    """A training checkpoint serialised (the caller stores it)."""
    buf = io.BytesIO()
    torch.save(checkpoint, buf)
    return buf.getvalue()


def checkpoint_from_bytes(data: bytes) -> Checkpoint:
    """A checkpoint written by `checkpoint_to_bytes` (trusted: it holds optimiser state)."""
    return torch.load(io.BytesIO(data), weights_only=False)


def _learning_rate(budget: StageBudget, step: int) -> float:
    """Linear warm-up over 5 % of the steps, then cosine decay to 5 % of the peak.

    A function of the step alone, so a resumed run (even with a longer budget) continues it.
    """
    warm = max(1, budget.steps // 20)
    if step < warm:
        return budget.lr * (step + 1) / warm
    frac = min(1.0, (step - warm) / max(1, budget.steps - warm))
    return budget.lr * (0.05 + 0.95 * 0.5 * (1.0 + math.cos(math.pi * frac)))


def _fit(
    stage: str,
    modules: dict[str, nn.Module],
    trainable: list[nn.Parameter],
    step_loss: Callable[[], torch.Tensor],
    rng: np.random.Generator,
    budget: StageBudget,
    config: TrainConfig,
    resume: Checkpoint | None,
    on_checkpoint: Callable[[Checkpoint], None] | None,
    progress: Callable[[float, str], None] | None,
) -> list[dict[str, float]]:
    """The shared optimisation loop; returns the loss log (step, seconds, loss).

    `rng` draws the batches; its state is checkpointed with torch's, so a resumed run sees
    the crops an uninterrupted one would have.
    """
    opt = torch.optim.AdamW(trainable, lr=budget.lr, weight_decay=1e-4)
    step, elapsed, log = 0, 0.0, []
    if resume is not None and resume.get("stage") == stage:
        for name, module in modules.items():
            module.load_state_dict(resume["modules"][name])
        opt.load_state_dict(resume["optimizer"])
        step, elapsed, log = resume["step"], resume["elapsed_s"], list(resume["log"])
        torch.set_rng_state(resume["torch_rng"])
        rng.bit_generator.state = resume["numpy_rng"]
    start = time.monotonic() - elapsed
    running = 0.0
    while step < budget.steps and (time.monotonic() - start) < budget.minutes * 60:
        for group in opt.param_groups:
            group["lr"] = _learning_rate(budget, step)
        loss = step_loss()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        nn.utils.clip_grad_norm_(trainable, 1.0)
        opt.step()
        step += 1
        running = loss.item() if step == 1 else 0.95 * running + 0.05 * loss.item()
        if step % 10 == 0 or step == budget.steps:
            log.append({"step": step, "seconds": time.monotonic() - start, "loss": running})
        if progress is not None:
            frac = max(step / budget.steps, (time.monotonic() - start) / (budget.minutes * 60))
            progress(min(frac, 1.0), f"{stage} loss {running:.4f}")
        if on_checkpoint is not None and step % config.checkpoint_every == 0:
            on_checkpoint(
                {
                    "stage": stage,
                    "modules": {k: m.state_dict() for k, m in modules.items()},
                    "optimizer": opt.state_dict(),
                    "step": step,
                    "elapsed_s": time.monotonic() - start,
                    "log": log,
                    "torch_rng": torch.get_rng_state(),
                    "numpy_rng": rng.bit_generator.state,
                }
            )
    return log


def train_regressor(
    train: DepthPairs,
    config: TrainConfig,
    seed: int,
    device: torch.device,
    resume: Checkpoint | None = None,
    on_checkpoint: Callable[[Checkpoint], None] | None = None,
    progress: Callable[[float, str], None] | None = None,
    initial: ResidualUNet | None = None,
) -> tuple[ResidualUNet, list[dict[str, float]]]:
    """Trains the residual U-Net baseline on crops of `train`, from `initial` (fine-tuning
    trained weights) or from a fresh initialisation."""
    torch.manual_seed(seed)
    model = (initial or ResidualUNet(config.regressor)).to(device).train()
    sampler = CropSampler(train, config.crop, seed, config.loss_mask_threshold_n)

    def step_loss() -> torch.Tensor:
        deg, deg_valid, clean, mask, side = sampler.batch(config.batch, device)
        weight = loss_weights(clean, sampler.resolution, config.loss_slope_power)
        return masked_mse(model(deg, deg_valid, side), clean, mask, weight)

    log = _fit(
        "regressor",
        {"regressor": model},
        list(model.parameters()),
        step_loss,
        sampler.rng,
        config.regressor_budget,
        config,
        resume,
        on_checkpoint,
        progress,
    )
    return model.eval(), log


def train_vae(
    train: DepthPairs,
    config: TrainConfig,
    seed: int,
    device: torch.device,
    resume: Checkpoint | None = None,
    on_checkpoint: Callable[[Checkpoint], None] | None = None,
    progress: Callable[[float, str], None] | None = None,
    refines: ResidualUNet | None = None,
) -> tuple[DepthVAE, list[dict[str, float]]]:
    """Trains the KL autoencoder: clean depth -> latent -> clean depth, the decoder guided by
    the degraded depth (the `refines` regressor's estimate from it, when given); then sets its
    latent scale so latents have unit variance."""
    torch.manual_seed(seed + 1)
    vae = DepthVAE(config.vae).to(device)
    sampler = CropSampler(train, config.crop, seed + 1, config.loss_mask_threshold_n)

    calls = [resume["step"] if resume is not None and resume.get("stage") == "vae" else 0]
    warm_steps = max(1.0, config.kl_warmup_fraction * config.vae_budget.steps)

    def step_loss() -> torch.Tensor:
        deg, deg_valid, clean, mask, side = sampler.batch(config.batch, device)
        deg = guide_depth(refines, deg, deg_valid, side)
        posterior = vae.encode(clean, deg_valid, deg)
        z = posterior.sample()
        recon = vae.decode(z, deg, deg_valid, side)
        kl_weight = config.kl_weight * min(1.0, calls[0] / warm_steps)
        calls[0] += 1
        kl_per_pixel = posterior.kl().mean() / (clean.shape[-2] * clean.shape[-1])
        return masked_mse(recon, clean, mask) + kl_weight * kl_per_pixel

    log = _fit(
        "vae",
        {"vae": vae},
        list(vae.parameters()),
        step_loss,
        sampler.rng,
        config.vae_budget,
        config,
        resume,
        on_checkpoint,
        progress,
    )
    vae.eval()
    with torch.no_grad():
        deg, deg_valid, clean, _, side = sampler.batch(max(config.batch, 8), device)
        deg = guide_depth(refines, deg, deg_valid, side)
        z = vae.encode(clean, deg_valid, deg).mean
        vae.latent_scale.fill_(1.0 / float(z.std().clamp_min(1e-6)))
    return vae, log


def train_ldm(
    train: DepthPairs,
    vae: DepthVAE,
    config: TrainConfig,
    seed: int,
    device: torch.device,
    resume: Checkpoint | None = None,
    on_checkpoint: Callable[[Checkpoint], None] | None = None,
    progress: Callable[[float, str], None] | None = None,
    refines: ResidualUNet | None = None,
) -> tuple[LatentUNet, ControlNet, list[dict[str, float]]]:
    """Trains U-Net and ControlNet together (no pretrained U-Net exists to freeze) with the
    v-prediction objective on latents of clean depth, conditioned on the degraded depth (the
    `refines` regressor's estimate from it, when given)."""
    torch.manual_seed(seed + 2)
    unet = LatentUNet(config.unet).to(device)
    control = ControlNet(config.unet).to(device)
    control.copy_encoder_from(unet)
    schedule = DDPMSchedule()
    alphas = torch.from_numpy(schedule.alphas_cumprod).float().to(device)
    sampler = CropSampler(train, config.crop, seed + 2, config.loss_mask_threshold_n)
    vae.eval().requires_grad_(False)

    def step_loss() -> torch.Tensor:
        deg, deg_valid, clean, _, side = sampler.batch(config.batch, device)
        deg = guide_depth(refines, deg, deg_valid, side)
        with torch.no_grad():
            z0 = vae.encode(clean, deg_valid, deg).mean * vae.latent_scale
        t_max = min(config.ldm_max_timestep, schedule.num_train_steps)
        t = torch.randint(0, t_max, (z0.shape[0],), device=device)
        noise = torch.randn_like(z0)
        a = alphas[t].sqrt()[:, None, None, None]
        s = (1 - alphas[t]).sqrt()[:, None, None, None]
        zt = a * z0 + s * noise
        v_target = a * noise - s * z0
        residuals = control(zt, t, control.hint_of(deg, deg_valid, side))
        v_pred = unet(zt, t, residuals)
        return ((v_pred - v_target) ** 2).mean()

    log = _fit(
        "ldm",
        {"unet": unet, "controlnet": control},
        list(unet.parameters()) + list(control.parameters()),
        step_loss,
        sampler.rng,
        config.ldm_budget,
        config,
        resume,
        on_checkpoint,
        progress,
    )
    return unet.eval(), control.eval(), log


def train_finetune(
    train: DepthPairs,
    models: LDMModels,
    config: TrainConfig,
    seed: int,
    device: torch.device,
    resume: Checkpoint | None = None,
    on_checkpoint: Callable[[Checkpoint], None] | None = None,
    progress: Callable[[float, str], None] | None = None,
) -> tuple[LDMModels, list[dict[str, float]]]:
    """End-to-end fine-tuning (as Garcia et al. 2024 do for diffusion depth estimators): the
    whole sampler - encode, noise to the strength, unrolled DDIM steps, guided decode - is
    trained on the depth error it leaves, so the few-step sampler is optimised for the depth
    the mesh update reads rather than for a latent objective two steps removed from it."""
    torch.manual_seed(seed + 3)
    sampler = CropSampler(train, config.crop, seed + 3, config.loss_mask_threshold_n)
    parts = {"vae": models.vae, "unet": models.unet, "controlnet": models.controlnet}
    for part in parts.values():
        part.train().requires_grad_(True)

    def step_loss() -> torch.Tensor:
        deg, deg_valid, clean, mask, side = sampler.batch(config.batch, device)
        steps = int(sampler.rng.choice(config.finetune_steps))
        noise = torch.randn(latent_shape(deg), device=device)
        pred = sample_depth(models, deg, deg_valid, steps, config.finetune_strength, noise, side)
        weight = loss_weights(clean, sampler.resolution, config.loss_slope_power)
        return masked_mse(pred, clean, mask, weight)

    trainable = [p for part in parts.values() for p in part.parameters()]
    log = _fit(
        "finetune", parts, trainable, step_loss, sampler.rng, config.finetune_budget, config,
        resume,
        on_checkpoint, progress,
    )
    for part in parts.values():
        part.eval()
    return models, log
