"""The network stages of a run (regressor, VAE, LDM, end-to-end fine-tuning): each trains from
a checkpoint when resuming, writes its weights and returns its report entry.

A `StageRunner` holds what the stages hand on to each other: the regressor the LDM refines and
the VAE and U-Net + ControlNet the fine-tuning starts from, loaded from --init weights or from
finished stages of the run.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import asdict, dataclass
from typing import Any

from pipeline.enhance.models.controlnet import ControlNet
from pipeline.enhance.models.regressor import ResidualUNet
from pipeline.enhance.models.unet import LatentUNet
from pipeline.enhance.models.vae import DepthVAE
from pipeline.enhance.pipelines.depth_ldm import LDMModels
from pipeline.enhance.training import loop as tl
from pipeline.enhance.training import stages as tr
from pipeline.enhance.training.config import TrainConfig
from pipeline.enhance.training.data import DepthPairs
from pipeline.enhance.training.plan import WeightsStore
from pipeline.enhance.training.validate import validate_ldm, validate_regressor
from pipeline.enhance.weights.loading import (
    ldm_to_bytes,
    load_ldm,
    load_regressor,
    load_vae,
    weights_to_bytes,
)

StageProgress = Callable[[float, str], None]
"""Told a stage's progress: (fraction done, a short text such as the loss)."""
StageBar = Callable[[str], AbstractContextManager[StageProgress]]
"""Opens the progress display of the named stage for as long as it runs."""


@dataclass
class StageRunner:
    """One run's network stages and what they pass on."""

    out: WeightsStore
    cfg: TrainConfig
    seed: int
    device: Any
    """A torch.device."""
    resume: bool
    train_pairs: DepthPairs
    val_pairs: DepthPairs
    bar: StageBar
    regressor: ResidualUNet | None = None
    initial_regressor: ResidualUNet | None = None
    """Where the regressor stage starts (--init); None: a fresh network."""
    vae: DepthVAE | None = None
    nets: tuple[LatentUNet, ControlNet] | None = None

    def start_from(self, init: WeightsStore | None) -> None:
        """Loads --init weights, then a regressor a resumed run already finished."""
        if init is not None:
            self.initial_regressor = self.regressor = load_regressor(
                init.read("regressor.safetensors"))
            self._set_ldm(load_ldm(init.read("vae.safetensors"), init.read("ldm.safetensors")))
        trained = self._finished("regressor")
        if trained is not None:
            self.regressor = load_regressor(trained)
        if self.regressor is not None:
            self.regressor.to(self.device)

    def run(self, stage: str) -> dict[str, Any] | None:
        """Trains `stage` (None when a resumed run finished it: its networks are loaded)."""
        done = self._finished(stage)
        if done is not None:
            self._load_finished(stage, done)
            return None
        checkpoint = f"checkpoints/{stage}.pt"
        state = (tl.checkpoint_from_bytes(self.out.read(checkpoint))
                 if self.resume and self.out.has(checkpoint) else None)
        started = time.monotonic()
        train = getattr(self, f"_train_{stage}")
        with self.bar(stage) as progress:
            log, weights, figures = train(
                state, lambda ck: self.out.write(checkpoint, tl.checkpoint_to_bytes(ck)),
                progress)
        self.out.write(_stage_file(stage), weights)
        return {
            "steps": log[-1]["step"] if log else 0,
            "lr": getattr(self.cfg, f"{stage}_budget").lr,
            "train_seconds": log[-1]["seconds"] if log else 0.0,
            "wall_seconds_this_run": time.monotonic() - started,
            "final_loss": log[-1]["loss"] if log else None,
            "loss_log": log[:: max(1, len(log) // 50)],
            "validation": figures,
        }

    def _train_regressor(self, state, save, progress):
        self.regressor, log = tr.train_regressor(
            self.train_pairs, self.cfg, self.seed, self.device, state, save, progress,
            self.initial_regressor)
        figures = validate_regressor(self.regressor, self.val_pairs, self.cfg.validation_views,
                                     self.device)
        return log, weights_to_bytes(self.regressor.state_dict(),
                                     asdict(self.regressor.config)), figures

    def _train_vae(self, state, save, progress):
        refines = self._refines("vae")
        self.vae, log = tr.train_vae(self.train_pairs, self.cfg, self.seed, self.device, state,
                                     save, progress, refines)
        figures = validate_ldm(None, self.vae, self.val_pairs, self.cfg.validation_views,
                               self.device, refines)
        return log, weights_to_bytes(self.vae.state_dict(), asdict(self.cfg.vae)), figures

    def _train_ldm(self, state, save, progress):
        if self.vae is None:
            raise ValueError("--stages: ldm needs the vae stage (or its weights in --out)")
        refines = self._refines("ldm")
        unet, control, log = tr.train_ldm(self.train_pairs, self.vae, self.cfg, self.seed,
                                          self.device, state, save, progress, refines)
        self.nets = (unet, control)
        figures = validate_ldm(self.nets, self.vae, self.val_pairs, self.cfg.validation_views,
                               self.device, refines)
        models = LDMModels(self.vae, unet, control, refines)
        return log, ldm_to_bytes(models, asdict(self.cfg.unet)), figures

    def _train_finetune(self, state, save, progress):
        if self.vae is None or self.nets is None:
            raise ValueError("--stages: finetune needs the vae and ldm stages (or their "
                             "weights in --out)")
        models, log = tr.train_finetune(
            self.train_pairs, LDMModels(self.vae, *self.nets, self._refines("finetune")),
            self.cfg, self.seed, self.device, state, save, progress)
        # The stage-wise weights stay beside the fine-tuned ones for comparison.
        for name in ("vae.safetensors", "ldm.safetensors"):
            if self.out.has(name):  # absent when fine-tuning --init
                self.out.write(f"pretrained/{name}", self.out.read(name))
        self._set_ldm(models)
        self.out.write("vae.safetensors",
                       weights_to_bytes(models.vae.state_dict(), asdict(self.cfg.vae)))
        self.out.write("ldm.safetensors", ldm_to_bytes(models, asdict(self.cfg.unet)))
        figures = validate_ldm(self.nets, self.vae, self.val_pairs, self.cfg.validation_views,
                               self.device, models.refines)
        return log, b"end-to-end fine-tuned: see vae.safetensors and ldm.safetensors", figures

    def _refines(self, stage: str) -> ResidualUNet | None:
        """The regressor the LDM's stages refine (None when the config does not)."""
        if not self.cfg.ldm_refines_regressor:
            return None
        if self.regressor is None:
            raise ValueError(f"--stages: {stage} refines the regressor: run the regressor "
                             "stage first (or give its weights in --out or --init)")
        return self.regressor

    def _finished(self, stage: str) -> bytes | None:
        name = _stage_file(stage)
        return self.out.read(name) if self.resume and self.out.has(name) else None

    def _load_finished(self, stage: str, weights: bytes) -> None:
        """A finished stage is kept; the VAE and LDM are loaded for the stages after them."""
        if stage == "vae":
            self.vae = load_vae(weights).to(self.device)
        if stage == "ldm" and self.vae is not None:
            self._set_ldm(load_ldm(self._finished("vae") or b"", weights))

    def _set_ldm(self, models: LDMModels) -> None:
        self.vae = models.vae.to(self.device)
        self.nets = (models.unet.to(self.device), models.controlnet.to(self.device))


def _stage_file(stage: str) -> str:
    """The file whose presence marks a stage finished (fine-tuning rewrites vae and ldm)."""
    return "finetune.done" if stage == "finetune" else f"{stage}.safetensors"
