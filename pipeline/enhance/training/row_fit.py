"""The training loop of the per-vertex networks (the twicing selector, the vertex gains): Adam
on random batches of rows, the learning rate cosine-decayed over the step budget, stopped by
the steps or the wall clock."""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import torch
from torch import nn


def fit_rows(
    model: nn.Module,
    rows: int,
    batch_loss: Callable[[torch.Tensor], torch.Tensor],
    steps: int,
    minutes: float,
    batch: int,
    lr: float,
    seed: int,
    progress: Callable[[float, str], None] | None = None,
    label: str = "",
) -> dict:
    """Trains `model` on `batch_loss` of (batch,) random row indices among `rows`; leaves it
    in eval mode and returns {steps, train_seconds, final_loss} (a running mean)."""
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    gen = torch.Generator().manual_seed(seed)
    t0, running, step = time.monotonic(), 0.0, 0
    while step < steps and time.monotonic() - t0 < minutes * 60:
        for group in opt.param_groups:
            group["lr"] = lr * 0.5 * (1 + np.cos(np.pi * step / steps))
        loss = batch_loss(torch.randint(0, rows, (batch,), generator=gen))
        opt.zero_grad()
        loss.backward()
        opt.step()
        step += 1
        running = 0.98 * running + 0.02 * loss.item() if step > 1 else loss.item()
        if progress is not None and step % 20 == 0:
            progress(step / steps, f"{label} loss {running:.4f}")
    model.eval()
    return {"steps": step, "train_seconds": time.monotonic() - t0, "final_loss": running}
