"""Twicing at several counts, and per-vertex features from which a network (the selector,
`models/twicing_selector.py`) weighs them: the learned counterpart of `adaptive_twicing`.

`adaptive_twicing` picks a count per vertex from an estimate of each count's bias measured
on a pilot that is itself blurred, so at creases and ears it underestimates the bias and
smooths too far. The selector reads the same kind of evidence at several neighbourhood sizes
and is trained on meshes with known truth to weigh the candidates so that the blend's
distance to the truth is least (`selector_training.py`). No torch here.
"""

from __future__ import annotations

from dataclasses import dataclass
from math import comb

import numpy as np
from numpy.typing import NDArray

from pipeline.enhance.baselines import mean_operator, twice_field
from pipeline.mesh import TriangleMesh, vertex_normals


@dataclass(frozen=True)
class TwicingBlendConfig:
    """The candidates and the features; the selector's weights are tied to it."""

    iterations: tuple[int, ...] = (5, 10, 15, 20, 30, 40, 60, 80, 120)
    """Iteration counts of the candidate twicings."""
    pilot_iterations: int = 30
    """Count of the pilot estimate on which the features are measured."""
    passes: int = 2
    """Passes of every twicing."""
    feature_rings: tuple[int, ...] = (0, 4, 12, 30)
    """Neighbour-averaging passes each feature is also given at (cumulative sizes)."""

    @property
    def feature_count(self) -> int:
        return (3 + 3 * len(self.iterations)) * len(self.feature_rings)


@dataclass(frozen=True)
class TwicingCandidates:
    """What the selector weighs, and what it reads."""

    vertices_m: NDArray[np.float64]
    """(K, V, 3) the mesh twiced at each of the config's counts."""
    features: NDArray[np.float32]
    """(V, F) per-vertex features, lengths in units of `noise_std_m`."""
    noise_std_m: float
    """Estimated standard deviation of the vertex noise along the normals."""


def twicing_candidates(mesh: TriangleMesh, config: TwicingBlendConfig) -> TwicingCandidates:
    """The candidates and their features.

    Per vertex, along the pilot's normal and divided by the estimated noise std: the squared
    residual of the mesh about the pilot, the pilot's curvature (signed and absolute, as the
    move of one neighbour-averaging step), and for each count the move it makes of the pilot
    (signed and squared: the bias it would add) and the squared distance of its result from
    the pilot. Each is given at every neighbourhood size in `feature_rings`.
    """
    m = mean_operator(mesh.faces, mesh.vertex_count)
    x = mesh.vertices_m
    # A fixed probe: the result depends on the mesh alone.
    probe = np.random.default_rng(0).normal(size=(len(x), 1))
    both = twice_field(m, np.hstack([x, probe]), config.pilot_iterations, config.passes, 0.5)
    pilot = both[:, :3]
    normals = vertex_normals(pilot, mesh.faces).astype(np.float64)
    residual = np.sum((x - pilot) * normals, axis=1)
    # The residual's variance is the noise's times the share the pilot removes of it.
    removed = float(np.mean((probe - both[:, 3:]) ** 2))
    noise_std_m = float(np.sqrt(np.mean(residual**2) / removed))
    columns = [
        (residual / noise_std_m) ** 2,
        np.sum((m @ pilot - pilot) * normals, axis=1) / noise_std_m,
    ]
    columns.append(np.abs(columns[-1]))
    candidates = []
    twiced = _twicings(m, np.hstack([x, pilot]), config.iterations, config.passes)
    for out in twiced:
        candidates.append(out[:, :3])
        pilot_move = np.sum((out[:, 3:] - pilot) * normals, axis=1) / noise_std_m
        from_pilot = np.sum((out[:, :3] - pilot) * normals, axis=1) / noise_std_m
        columns += [pilot_move**2, pilot_move, from_pilot**2]
    features = _multiscale(m, np.stack(columns, axis=1), config.feature_rings)
    return TwicingCandidates(np.stack(candidates), features.astype(np.float32), noise_std_m)


def _twicings(
    m, x: NDArray[np.float64], counts: tuple[int, ...], passes: int, lam: float = 0.5
) -> list[NDArray[np.float64]]:
    """`twice_field(m, x, k, passes, lam)` for every k in `counts`, from one run of smoothing steps.

    With L one smoothing step, `passes` passes of k steps are I - (I - L^k)^passes, a sum of
    powers L^(j k) (binomial expansion), so passes * max(counts) steps serve every count
    instead of passes * sum(counts).
    """
    needed = {j * k for k in counts for j in range(1, passes + 1)}
    powers, y = {0: x}, x
    for n in range(1, max(needed) + 1):
        y = y + lam * (m @ y - y)
        if n in needed:
            powers[n] = y
    return [
        sum((-1) ** (j + 1) * comb(passes, j) * powers[j * k] for j in range(1, passes + 1))
        for k in counts
    ]


def _multiscale(m, columns: NDArray[np.float64], rings: tuple[int, ...]) -> NDArray[np.float64]:
    """(V, C * len(rings)) the columns after each cumulative number of averaging passes."""
    out, done, a = [], 0, columns
    for r in rings:
        for _ in range(r - done):
            a = m @ a
        done = r
        out.append(a)
    return np.concatenate(out, axis=1)


def blend(candidates: NDArray[np.float64], weights: NDArray) -> NDArray[np.float64]:
    """(V, 3) per-vertex weighted sum of (K, V, 3) candidates with (V, K) weights."""
    return np.einsum("vk,kvc->vc", weights.astype(np.float64), candidates)
