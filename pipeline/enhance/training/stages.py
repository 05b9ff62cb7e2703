"""Training stages: the residual regressor, the VAE, the latent U-Net with its ControlNet, then
end-to-end fine-tuning of all three through the few-step sampler. Each builds its networks and
its loss and hands them to the shared loop (`train_loop.fit`), so each is resumable from the
checkpoints that loop writes.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from pipeline.enhance.models.controlnet import ControlNet
from pipeline.enhance.models.regressor import ResidualUNet
from pipeline.enhance.models.unet import LatentUNet
from pipeline.enhance.models.vae import DepthVAE
from pipeline.enhance.pipelines.depth_ldm import (
    LDMModels,
    guide_depth,
    latent_shape,
    sample_depth,
)
from pipeline.enhance.schedulers.ddpm import DDPMSchedule
from pipeline.enhance.training.config import TrainConfig
from pipeline.enhance.training.data import DepthPairs
from pipeline.enhance.training.loop import Checkpoint, CropSampler, fit, masked_mse


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
        return masked_mse(model(deg, deg_valid, side), clean, mask)

    log = fit(
        "regressor",
        {"regressor": model},
        list(model.parameters()),
        step_loss,
        sampler.rng,
        config.regressor_budget,
        config.checkpoint_every,
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
        posterior = vae.encode(clean, deg_valid)
        z = posterior.sample()
        recon = vae.decode(z, deg, deg_valid, side)
        kl_weight = config.kl_weight * min(1.0, calls[0] / warm_steps)
        calls[0] += 1
        kl_per_pixel = posterior.kl().mean() / (clean.shape[-2] * clean.shape[-1])
        return masked_mse(recon, clean, mask) + kl_weight * kl_per_pixel

    log = fit(
        "vae",
        {"vae": vae},
        list(vae.parameters()),
        step_loss,
        sampler.rng,
        config.vae_budget,
        config.checkpoint_every,
        resume,
        on_checkpoint,
        progress,
    )
    vae.eval()
    with torch.no_grad():
        deg, deg_valid, clean, _, side = sampler.batch(max(config.batch, 8), device)
        deg = guide_depth(refines, deg, deg_valid, side)
        z = vae.encode(clean, deg_valid).mean
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
            z0 = vae.encode(clean, deg_valid).mean * vae.latent_scale
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

    log = fit(
        "ldm",
        {"unet": unet, "controlnet": control},
        list(unet.parameters()) + list(control.parameters()),
        step_loss,
        sampler.rng,
        config.ldm_budget,
        config.checkpoint_every,
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
        return masked_mse(pred, clean, mask)

    trainable = [p for part in parts.values() for p in part.parameters()]
    log = fit(
        "finetune", parts, trainable, step_loss, sampler.rng, config.finetune_budget,
        config.checkpoint_every, resume, on_checkpoint, progress,
    )
    for part in parts.values():
        part.eval()
    return models, log
