"""What the held-out overlaps show: the evidence `align` asks of its corrections.

The overlap samples are split into two halves by place (alternate cubes of the world,
`AlignConfig.heldout_block_m`); the corrections solved from one half are judged by the gaps of
the other, each half in turn. A solve bends to the noise and mismatches of the samples it is
given; a true range offset or pose error shows in the held-out samples as well.
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from pipeline.reconstruct.align_solve import Matches, solve

if TYPE_CHECKING:
    from pipeline.reconstruct.align import AlignConfig

FloatArray = NDArray[np.float64]


def _solved_halves(matches: dict[tuple[int, int], Matches], camera_count: int,
                   config: AlignConfig, fixed: frozenset[int]) -> dict[bool, FloatArray]:
    """Per half, the corrections solved from that half's samples alone."""
    solved = {}
    for half in (False, True):
        subset = {pair: m.select(m.half == half) for pair, m in matches.items()}
        solved[half] = solve({p: m for p, m in subset.items() if len(m.rhs)}, camera_count,
                             config, fixed)
    return solved


def heldout_confirmation(matches: dict[tuple[int, int], Matches], camera_count: int,
                         config: AlignConfig, fixed: frozenset[int]) -> FloatArray:
    """(C,) per camera, how much of the change in its overlaps' gaps that the corrections
    solved from one half predict the other half shows: the least-squares scale of the
    predicted change on the held-out gaps, over the camera's pairs and both halves. 1: all
    of it, 0: none (NaN: no held-out samples that it moves).

    The change is the pair's, both cameras' corrections together: the overlaps show how two
    surfaces move against each other, and a camera's own share, set against the gap its
    partner's correction leaves, would show whenever the two turned together."""
    solved = _solved_halves(matches, camera_count, config, fixed)
    shown, predicted = np.zeros(camera_count), np.zeros(camera_count)
    for (i, j), m in matches.items():
        for half in (False, True):
            x = solved[not half]  # held out: solved without these samples
            rows = m.half == half
            change = m.row_i[rows] @ x[i] + m.row_j[rows] @ x[j]
            for own in (i, j):
                shown[own] += float(change @ m.rhs[rows])
                predicted[own] += float(change @ change)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(predicted > 0, shown / predicted, np.nan)


def _heldout_losses(matches: dict[tuple[int, int], Matches], camera_count: int,
                    config: AlignConfig, fixed: frozenset[int]) -> FloatArray:
    """(M,) the Huber loss of every sample under the corrections solved without its half."""
    solved = _solved_halves(matches, camera_count, config, fixed)
    losses = []
    for (i, j), m in matches.items():
        x = np.where(m.half[:, None], solved[False][i], solved[True][i])
        y = np.where(m.half[:, None], solved[False][j], solved[True][j])
        scale = np.abs(np.sum(m.row_i * x, axis=1) + np.sum(m.row_j * y, axis=1) - m.rhs)
        scale /= config.huber_m
        losses.append(np.where(scale <= 1.0, 0.5 * scale**2, scale - 0.5))
    return np.concatenate(losses) if losses else np.zeros(0)


def poses_shown(matches: dict[tuple[int, int], Matches], camera_count: int,
                config: AlignConfig, fixed: frozenset[int]) -> bool:
    """Whether pose touch-ups with the offsets explain held-out gaps better than the offsets
    alone: the mean gain in held-out loss per sample exceeds twice its standard error."""
    gain = (_heldout_losses(matches, camera_count, replace(config, poses=False), fixed)
            - _heldout_losses(matches, camera_count, config, fixed))
    if len(gain) < 2:
        return False
    return bool(gain.mean() > 2.0 * gain.std(ddof=1) / np.sqrt(len(gain)))
