"""Twicing at several counts, and per-vertex features from which a network (the selector,
`models/twicing_selector.py`) weighs them: the learned counterpart of `adaptive_twicing`.

`adaptive_twicing` picks a count per vertex from an estimate of each count's bias measured
on a pilot that is itself blurred, so at creases and ears it underestimates the bias and
smooths too far. The selector reads the same kind of evidence at several neighbourhood sizes
and is trained on meshes with known truth to weigh the candidates so that the blend's
distance to the truth is least (`training/selector.py`).

The smoothing steps, nearly all of the work, run behind one interface (`FieldOps`, in
`scale_selection_common`): in scipy and numpy on the host (`scale_selection_numpy`) or in
torch on a device (`scale_selection_torch`). Only `twicing_candidates` picks one, and neither
imports the other.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from math import comb
from typing import Any

import numpy as np
from numpy.typing import NDArray

from pipeline.enhance.presmooth import scale_selection_numpy
from pipeline.enhance.presmooth.scale_selection_common import FieldOps, along
from pipeline.geometry.mesh import TriangleMesh


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
    boundary_pilot_iterations: int = 10
    """Laplacian steps of the pilot on which open boundaries' one-sided umbrella offset is
    measured and then left out of every smoothing step
    (`pipeline.geometry.boundary.boundary_offset`), so that long twicings do not retract the
    boundary; 0 smooths boundary vertices like the rest."""

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


def twicing_candidates(
    mesh: TriangleMesh, config: TwicingBlendConfig, device: str | None = None
) -> TwicingCandidates:
    """The candidates and their features, in scipy and numpy on the host (None), or in torch
    on `device`.

    Per vertex, along the pilot's normal and divided by the estimated noise std: the squared
    residual of the mesh about the pilot, the pilot's curvature (signed and absolute, as the
    move of one neighbour-averaging step), and for each count the move it makes of the pilot
    (signed and squared: the bias it would add) and the squared distance of its result from
    the pilot. Each is given at every neighbourhood size in `feature_rings`.
    """
    ops = _field_ops(mesh, config.boundary_pilot_iterations, device)
    x = ops.to_field(mesh.vertices_m)
    # Every field below is a polynomial in the smoothing step applied to x, the pilot's
    # twicings included (`_step_polynomials`), so one run of steps on x gives them all.
    pilot_polynomial = _twicing_polynomial(config.pilot_iterations, config.passes)
    twicings = [_twicing_polynomial(k, config.passes) for k in config.iterations]
    pilot_twicings = [_product(t, pilot_polynomial) for t in twicings]
    fields = _step_polynomials(ops.step, x, [pilot_polynomial, *twicings, *pilot_twicings])
    pilot = fields[0]
    candidates = fields[1:1 + len(twicings)]
    pilot_twiced_fields = fields[1 + len(twicings):]
    # A fixed probe, stepped on its own: the result depends on the mesh alone.
    probe = ops.to_field(np.random.default_rng(0).normal(size=(mesh.vertex_count, 1)))
    (probe_pilot,) = _step_polynomials(ops.step, probe, [pilot_polynomial])
    normals = ops.normals(pilot)
    residual = along(x - pilot, normals)
    # The residual's variance is the noise's times the share the pilot removes of it.
    removed = float(((probe - probe_pilot) ** 2).mean())
    noise_std_m = float(np.sqrt(float((residual**2).mean()) / removed))
    columns = [(residual / noise_std_m) ** 2,
               along(ops.mean(pilot) - pilot, normals) / noise_std_m]
    columns.append(abs(columns[-1]))
    for candidate, pilot_twiced in zip(candidates, pilot_twiced_fields, strict=True):
        pilot_move = along(pilot_twiced - pilot, normals) / noise_std_m
        from_pilot = along(candidate - pilot, normals) / noise_std_m
        columns += [pilot_move**2, pilot_move, from_pilot**2]
    scales = _multiscale(ops.average, ops.columns(columns), config.feature_rings)
    features = np.concatenate([ops.to_numpy(a) for a in scales], axis=1)
    return TwicingCandidates(
        np.stack([ops.to_numpy(c) for c in candidates]), features, noise_std_m)


def _field_ops(mesh: TriangleMesh, boundary_pilot_iterations: int, device: str | None
               ) -> FieldOps:
    """The mesh's `FieldOps`: scipy and numpy on the host (None), or torch on `device`."""
    if device is None:
        return scale_selection_numpy.mesh_field_ops(mesh, boundary_pilot_iterations)
    from pipeline.enhance.presmooth import scale_selection_torch

    return scale_selection_torch.mesh_field_ops(mesh, boundary_pilot_iterations, device)


def _twicing_polynomial(count: int, passes: int) -> dict[int, int]:
    """`passes` passes of `count` smoothing steps, I - (I - L^count)^passes, as its
    coefficients {power: coefficient} (binomial expansion): `twice_field(m, x, count,
    passes, 0.5)` is that sum of powers of L applied to x (count 0: {0: 1}, x itself)."""
    out: dict[int, int] = {}
    for j in range(1, passes + 1):
        out[j * count] = out.get(j * count, 0) + (-1) ** (j + 1) * comb(passes, j)
    return out


def _product(p: dict[int, int], q: dict[int, int]) -> dict[int, int]:
    """The polynomial p q, coefficients by power."""
    out: dict[int, int] = {}
    for a, ca in p.items():
        for b, cb in q.items():
            out[a + b] = out.get(a + b, 0) + ca * cb
    return out


def _step_polynomials(step: Callable[[Any], Any], x, polynomials: list[dict[int, int]]
                      ) -> list:
    """p(A) x = Σ_n c_n A^n x for each polynomial p = {n: c_n}, A one `step`, from one run
    of as many steps as the highest power.

    Where steps leave out a boundary offset c (`leaving_out`), a step is affine, A y = L y -
    c / 2. The polynomials here have coefficients that sum to 1 (twicings, and their
    products), so they are affine combinations, which affine maps keep: a twicing of the
    pilot is the product polynomial applied to x, which gives what stepping the pilot beside
    x would, to rounding, with half the columns. These are not `twice_field` with offset
    steps, which holds a boundary further.
    """
    terms: dict[int, list[tuple[int, int]]] = {}
    for i, polynomial in enumerate(polynomials):
        for n, c in polynomial.items():
            terms.setdefault(n, []).append((i, c))
    sums: list[Any] = [0] * len(polynomials)
    y = x
    for n in range(max(terms) + 1):
        if n > 0:
            y = step(y)
        for i, c in terms.get(n, ()):
            sums[i] = sums[i] + c * y
    return sums


def _multiscale(average: Callable[[Any], Any], columns, rings: tuple[int, ...]) -> list:
    """(V, C) the columns after each cumulative number of averaging passes in `rings`."""
    out, done, a = [], 0, columns
    for r in rings:
        for _ in range(r - done):
            a = average(a)
        done = r
        out.append(a)
    return out


def blend(candidates: NDArray[np.float64], weights: NDArray) -> NDArray[np.float64]:
    """(V, 3) per-vertex weighted sum of (K, V, 3) candidates with (V, K) weights."""
    return np.einsum("vk,kvc->vc", weights.astype(np.float64), candidates)
