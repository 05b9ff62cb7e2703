"""Training configurations: the data, network sizes and per-stage budgets of a run, the named
configurations (tiny, small, large) and the budget edits the CLI applies to them."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

from pipeline.enhance.models.regressor import RegressorConfig
from pipeline.enhance.models.unet import UNetConfig
from pipeline.enhance.models.vae import VAEConfig
from pipeline.enhance.models.vertex_gain import VertexGainConfig
from pipeline.enhance.training.data import SAME_SURFACE_N, DataConfig
from pipeline.enhance.training.gain import GainTrainConfig
from pipeline.enhance.training.selector import SelectorConfig, SelectorTrainConfig


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
    gain: GainTrainConfig = field(default_factory=GainTrainConfig)
    """The vertex gain networks' data and budget (their own stage, after the networks)."""
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
    image's pixels), so that it is on the scale of the mean per-pixel loss: heavier, the
    posterior collapses and the decoder, which also sees the degraded depth, ignores the
    latent."""
    kl_warmup_fraction: float = 0.5
    """The KL weight ramps up from 0 over this fraction of the VAE's steps (against collapse)."""
    ldm_max_timestep: int = 600
    """Training timesteps are drawn below this: sampling starts part-way (strength <= 0.6),
    so capacity is not spent on the pure-noise end of the schedule."""
    validation_views: int = 24
    """Validation images scored at the end of each stage."""
    loss_mask_threshold_n: float = SAME_SURFACE_N
    """Pixels where an input is further than this (normalised depth) from the clean render
    are left out of the losses (`same_surface_mask`): another surface is seen there.
    `BULK_SURFACE_N` (`--loss-mask 0.02`, the shipped weights' recipe) leaves out the rest of
    those pixels, which still carry much of the squared loss at the default."""
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
        gain=GainTrainConfig(
            model=VertexGainConfig(hidden=8), with_procedural=True, draws_per_mesh=1,
            edge_fraction=(0.03, 0.04),
            resolution=32, vertices_per_draw=2000, steps=5, batch=256,
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
    # About an hour on 2 CPU cores with data and validation, most of it end-to-end.
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
    # The shipped weights' first training and selector stage (MODEL_CARD.md): the small
    # networks with 4x the batch and 2.7x the poses; minutes on a GPU, a day on 2 CPU cores.
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
    gain = replace(config.gain, steps=max(1, int(config.gain.steps * factor)),
                   minutes=config.gain.minutes * factor)
    return _each_budget(
        replace(config, selector=selector, gain=gain),
        lambda b: replace(b, steps=max(1, int(b.steps * factor)), minutes=b.minutes * factor),
    )


def capped(config: TrainConfig, minutes: float) -> TrainConfig:
    """The same configuration with every network stage's wall-clock limit set to `minutes`
    (steps unchanged, so the learning-rate schedule is the step budget's)."""
    return _each_budget(config, lambda b: replace(b, minutes=minutes))


def with_lr(config: TrainConfig, lr: float) -> TrainConfig:
    """The same configuration with every network stage's peak learning rate set to `lr`."""
    return _each_budget(config, lambda b: replace(b, lr=lr))
