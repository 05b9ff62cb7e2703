"""The optimisation loop the training stages share, and what it feeds on: crops of the depth
pairs, the masked depth loss, the learning-rate schedule and checkpoints.

The loop is time- and step-bounded, seeded, and resumable: every `checkpoint_every` steps it
hands a state dict to a callback (the CLI writes it) and accepts one back to continue.
"""

from __future__ import annotations

import io
import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
import torch.nn.functional as nnf
from torch import nn

from pipeline.enhance.models.common import RESIDUAL_SCALE, side_inputs
from pipeline.enhance.training.config import StageBudget
from pipeline.enhance.training.data import SAME_SURFACE_N, DepthPairs, same_surface_mask

Checkpoint = dict[str, Any]


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


def slope_weights(clean_n: torch.Tensor, resolution: int, power: int) -> torch.Tensor:
    """(B, 1, H, W) cos^power of the slant of the (B, 1, H, W) clean surface to the view:
    cos = 1 / sqrt(1 + |grad z|²) with the slope from central differences of the orthographic
    render, whose normalised depth unit is the image side (`resolution` pixels)."""
    c = nnf.pad(clean_n, (1, 1, 1, 1), mode="replicate")
    gx = (c[..., 1:-1, 2:] - c[..., 1:-1, :-2]) * (0.5 * resolution)
    gy = (c[..., 2:, 1:-1] - c[..., :-2, 1:-1]) * (0.5 * resolution)
    return (1.0 + gx**2 + gy**2) ** (-0.5 * power)

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


def fit(
    stage: str,
    modules: dict[str, nn.Module],
    trainable: list[nn.Parameter],
    step_loss: Callable[[], torch.Tensor],
    rng: np.random.Generator,
    budget: StageBudget,
    checkpoint_every: int,
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
        if on_checkpoint is not None and step % checkpoint_every == 0:
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
