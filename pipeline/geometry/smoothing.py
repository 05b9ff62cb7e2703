"""Classical mesh denoisers (no torch): the baselines the enhancement is measured against, and
the mean operator and twicing its pre-smoothing builds on."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from pipeline.geometry.mesh import TriangleMesh, vertex_normals


def adjacency(faces: NDArray[np.int32], vertex_count: int) -> sp.csr_matrix:
    """(V, V) symmetric 0/1 vertex adjacency from the faces' edges."""
    i = np.concatenate([faces[:, 0], faces[:, 1], faces[:, 2]])
    j = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0]])
    a = sp.coo_matrix((np.ones(len(i)), (i, j)), shape=(vertex_count, vertex_count)).tocsr()
    a = ((a + a.T) > 0).astype(np.float64)
    return a.tocsr()


def mean_operator(faces: NDArray[np.int32], vertex_count: int) -> sp.csr_matrix:
    """Row-normalised adjacency: (M @ v)[i] is the mean of i's neighbours (isolated: itself)."""
    a = adjacency(faces, vertex_count)
    deg = np.asarray(a.sum(axis=1)).ravel()
    lonely = deg == 0
    a = a + sp.diags(lonely.astype(np.float64))
    return sp.diags(1.0 / np.maximum(deg, 1.0)) @ a


def laplacian_smooth(mesh: TriangleMesh, iterations: int, lam: float = 0.5) -> TriangleMesh:
    """Uniform-weight Laplacian smoothing: v += lam * (mean of neighbours - v), repeated."""
    if iterations < 0:
        raise ValueError(f"iterations must be >= 0, got {iterations}")
    m = mean_operator(mesh.faces, mesh.vertex_count)
    return mesh.with_vertices(twice_field(m, mesh.vertices_m, iterations, 1, lam))


def twicing_smooth(
    mesh: TriangleMesh, iterations: int, passes: int = 2, lam: float = 0.5
) -> TriangleMesh:
    """Laplacian smoothing applied again to what it left: out += L^k(x - out), `passes` times.

    One pass is `laplacian_smooth`; two are Tukey's twicing. With h the response of k
    iterations at a frequency, p passes respond 1 - (1 - h)^p: the low frequencies one pass
    shrinks (the shape) are kept, so k can be large enough to average noise over wide
    neighbourhoods without the shrinkage that stops plain Laplacian smoothing near 10.
    """
    if iterations < 0 or passes < 1:
        raise ValueError(f"iterations must be >= 0 and passes >= 1, got {iterations}, {passes}")
    m = mean_operator(mesh.faces, mesh.vertex_count)
    return mesh.with_vertices(twice_field(m, mesh.vertices_m, iterations, passes, lam))


def twice_field(m: sp.csr_matrix, x: NDArray, iterations: int, passes: int, lam: float) -> NDArray:
    """`twicing_smooth` of a (V, C) per-vertex field with the mean operator `m`."""
    out = np.zeros_like(x)
    for _ in range(passes):
        r = x - out
        for _ in range(iterations):
            r = r + lam * (m @ r - r)
        out = out + r
    return out


@dataclass(frozen=True)
class AdaptiveTwicingConfig:
    """`adaptive_twicing`: which counts, and how the choice is estimated."""

    iterations: tuple[int, ...] = (10, 20, 30, 40, 60, 80)
    """Candidate iteration counts of twicing."""
    pilot_iterations: int = 30
    """Count of the pilot estimate on which each candidate's bias is measured."""
    cost_smoothing: int = 20
    """Neighbour-averaging passes over the estimated errors, so neighbours choose alike."""
    passes: int = 2
    """Passes of every twicing."""


def adaptive_twicing(mesh: TriangleMesh, config: AdaptiveTwicingConfig) -> TriangleMesh:
    """Twicing with its iteration count chosen per vertex by the least estimated squared error.

    A count's bias at a vertex is estimated as how far that count moves a pilot estimate
    (twicing at `pilot_iterations`) along the pilot's normals, where the shape bends more than
    the filter keeps; its noise as the variance of the mesh about the pilot times the count's
    noise gain (the mean square of white noise after the same filter). Where the surface is
    smooth wide counts win, at ears and creases narrow ones.
    """
    m = mean_operator(mesh.faces, mesh.vertex_count)
    x = mesh.vertices_m
    pilot = twice_field(m, x, config.pilot_iterations, config.passes, 0.5)
    normals = vertex_normals(pilot, mesh.faces).astype(np.float64)
    noise_var = float(np.mean(np.sum((x - pilot) * normals, axis=1) ** 2))
    # A fixed probe: the result depends on the mesh alone.
    probe = np.random.default_rng(0).normal(size=(len(x), 1))
    results, costs = [], []
    for k in config.iterations:
        out = twice_field(m, np.hstack([x, pilot, probe]), k, config.passes, 0.5)
        results.append(out[:, :3])
        bias_sq = np.sum((out[:, 3:6] - pilot) * normals, axis=1) ** 2
        for _ in range(config.cost_smoothing):
            bias_sq = m @ bias_sq
        costs.append(bias_sq + noise_var * float(np.mean(out[:, 6] ** 2)))
    choice = np.argmin(np.stack(costs), axis=0)
    return mesh.with_vertices(np.stack(results)[choice, np.arange(len(x))])


def taubin_smooth(
    mesh: TriangleMesh, iterations: int, lam: float = 0.5, mu: float = -0.53
) -> TriangleMesh:
    """Taubin lambda|mu smoothing (shrink, then inflate): one iteration is one pair of steps."""
    if iterations < 0:
        raise ValueError(f"iterations must be >= 0, got {iterations}")
    m = mean_operator(mesh.faces, mesh.vertex_count)
    v = mesh.vertices_m.copy()
    for _ in range(iterations):
        v = v + lam * (m @ v - v)
        v = v + mu * (m @ v - v)
    return mesh.with_vertices(v)


def bilateral_denoise(mesh: TriangleMesh, iterations: int, rings: int = 2) -> TriangleMesh:
    """Bilateral mesh denoising (Fleishman, Drori, Cohen-Or 2003) over k-ring neighbourhoods.

    Each vertex moves along its normal by the bilateral-weighted mean of its neighbours' heights
    above the tangent plane; the spatial sigma is the mean neighbour distance, the range sigma
    the spread of heights, both per vertex.
    """
    if iterations < 0:
        raise ValueError(f"iterations must be >= 0, got {iterations}")
    a = adjacency(mesh.faces, mesh.vertex_count)
    ring = a.copy()
    for _ in range(rings - 1):
        ring = ((ring + ring @ a) > 0).astype(np.float64)
    ring = ring.tocoo()
    keep = ring.row != ring.col
    i, j = ring.row[keep], ring.col[keep]
    v = mesh.vertices_m.copy()
    n_vertices = mesh.vertex_count
    for _ in range(iterations):
        normals = vertex_normals(v, mesh.faces).astype(np.float64)
        d = v[j] - v[i]
        dist = np.linalg.norm(d, axis=1)
        height = np.sum(d * normals[i], axis=1)
        sigma_c = np.bincount(i, dist, n_vertices) / np.maximum(np.bincount(i, None, n_vertices), 1)
        mean_h = np.bincount(i, height, n_vertices) / np.maximum(
            np.bincount(i, None, n_vertices), 1
        )
        var_h = np.bincount(i, (height - mean_h[i]) ** 2, n_vertices) / np.maximum(
            np.bincount(i, None, n_vertices), 1
        )
        sigma_s = np.sqrt(var_h) + 1e-12
        w = np.exp(-(dist**2) / (2 * sigma_c[i] ** 2 + 1e-30)) * np.exp(
            -(height**2) / (2 * sigma_s[i] ** 2)
        )
        offset = np.bincount(i, w * height, n_vertices) / np.maximum(
            np.bincount(i, w, n_vertices), 1e-30
        )
        v = v + normals * offset[:, None]
    return mesh.with_vertices(v)
