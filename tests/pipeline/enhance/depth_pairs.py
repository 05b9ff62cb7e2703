"""Depth pairs the enhancement's tests build themselves."""

from __future__ import annotations

import numpy as np

from pipeline.enhance.training.data import DepthPairs


def ramp_pairs(n: int = 3, side: int = 40) -> DepthPairs:
    """Pairs whose base depth is a unique ramp (each window identifiable by its minimum) and
    whose clean depth is the base plus 0.01; the mask covers the left 70 % of each image."""
    base = (np.arange(n * side * side, dtype=np.float32) / (n * side * side)).reshape(n, side, side)
    valid = np.ones_like(base, bool)
    mask = np.zeros_like(valid)
    mask[:, :, : int(0.7 * side)] = True
    return DepthPairs(base, valid, base.copy(), base + 0.01, mask, np.zeros_like(valid),
                      ("ramp",) * n)
