"""Classical mesh denoisers (no torch): the baselines the enhancement is measured against, and
the mean operator and twicing its pre-smoothing builds on."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from pipeline.geometry.mesh import TriangleMesh, face_normals, vertex_normals
from pipeline.geometry.repair import face_areas, faces_sharing_vertices


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


@dataclass(frozen=True)
class NormalFilteringConfig:
    """`bilateral_normal_filtering`: how the face normals are filtered and the vertices fitted."""

    normal_passes: int = 10
    """Passes of bilateral averaging of the face normals."""
    range_sigma: float = 0.35
    """sigma_s, the normal-likeness width: of the distance |n_f - n_g| between unit normals."""
    vertex_iterations: int = 20
    """Rounds of moving the vertices to fit the filtered normals."""
    spatial_sigma_m: float | None = None
    """sigma_c, of the distance between face centroids, metres; None: the mean distance between
    the centroids of faces that share an edge (Zheng et al.'s default)."""

    def __post_init__(self) -> None:
        if self.normal_passes < 0 or self.vertex_iterations < 0:
            raise ValueError("bilateral_normal_filtering: passes and iterations must be >= 0")
        if not self.range_sigma > 0 or (self.spatial_sigma_m is not None
                                        and not self.spatial_sigma_m > 0):
            raise ValueError("bilateral_normal_filtering: the sigmas must be > 0")


def bilateral_normal_filtering(mesh: TriangleMesh, config: NormalFilteringConfig
                               ) -> TriangleMesh:
    """Bilateral normal filtering (Zheng, Fu, Au, Tai 2011): the face normals averaged over the
    faces sharing a vertex with each, weighted by area, centroid distance and normal likeness,
    `normal_passes` times; then the vertices fitted to them (`fit_vertices_to_normals`).

    The range weight is what keeps a crease: faces across it differ in normal by more than
    sigma_s and barely count, so each side averages its own noise away. The enhance stage ends
    with the same filter in torch (`pipeline.enhance.update.normal_filter`, on its device and
    set for the faint noise the view update leaves); this one is the classical baseline."""
    passes = face_normal_passes(mesh, config.range_sigma, config.spatial_sigma_m)
    normals = face_normals(mesh.vertices_m, mesh.faces)
    for _ in range(config.normal_passes):
        normals = next(passes)
    return mesh.with_vertices(fit_vertices_to_normals(mesh, normals, config.vertex_iterations))


def face_normal_passes(mesh: TriangleMesh, range_sigma: float,
                       spatial_sigma_m: float | None = None) -> Iterator[NDArray[np.float64]]:
    """(F, 3) the unit face normals after each pass of bilateral averaging, without end: a
    sweep over the pass count reads them as they come. The spatial weights (area times the
    centroid-distance Gaussian) are the input mesh's, as the vertices move only afterwards."""
    sharing = faces_sharing_vertices(mesh.faces, mesh.vertex_count).tocsr()
    sharing.sort_indices()
    row_sizes, cols = np.diff(sharing.indptr), sharing.indices

    def pair_dot(field: NDArray[np.float64]) -> NDArray[np.float64]:
        """(P,) each face pair's dot product of `field`'s rows; coordinate by coordinate, the
        rows' side repeated in order, cheaper than gathering (P, 3) rows twice."""
        return sum((np.repeat(column, row_sizes) * column[cols]
                    for column in np.ascontiguousarray(field.T)),
                   start=np.zeros(len(cols)))

    centroids_m = mesh.vertices_m[mesh.faces].mean(axis=1)
    centroids_m -= centroids_m.mean(axis=0)  # the distances from products cancel less
    squared_m2 = np.sum(centroids_m**2, axis=1)
    gap_m2 = np.maximum(np.repeat(squared_m2, row_sizes) + squared_m2[cols]
                        - 2.0 * pair_dot(centroids_m), 0.0)
    if spatial_sigma_m is None:
        # Two shared vertices: the faces share an edge.
        spatial_sigma_m = float(np.sqrt(gap_m2[sharing.data == 2]).mean())
    near = face_areas(mesh.vertices_m, mesh.faces)[cols] * np.exp(
        -gap_m2 / (2.0 * spatial_sigma_m**2))
    normals = face_normals(mesh.vertices_m, mesh.faces)
    shape = (mesh.face_count, mesh.face_count)
    while True:
        # |n_f - n_g|² = 2 - 2 n_f·n_g for unit normals.
        weights = near * np.exp((pair_dot(normals) - 1.0) / range_sigma**2)
        summed = sp.csr_matrix((weights, cols, sharing.indptr), shape=shape) @ normals
        length = np.linalg.norm(summed, axis=1, keepdims=True)
        normals = np.divide(summed, length, out=np.zeros_like(summed), where=length > 0)
        yield normals


def fit_vertices_to_normals(mesh: TriangleMesh, normals: NDArray[np.float64],
                            iterations: int) -> NDArray[np.float64]:
    """(V, 3) the vertices moved so that the faces lie across `normals` (F, 3): each round, a
    vertex moves by the mean over its faces of n_f (n_f · (c_f - x)), its offset to the face's
    centroid plane (Sun et al. 2007), so along the normals only and not sliding in the surface.

    The normals are fixed, so each vertex's Σ n_f n_fᵀ is formed once and a round costs two
    sparse products."""
    corners = mesh.faces.ravel()
    incidence = sp.csr_matrix(
        (np.ones(len(corners)), (corners, np.repeat(np.arange(mesh.face_count), 3))),
        shape=(mesh.vertex_count, mesh.face_count))
    face_count = np.maximum(np.asarray(incidence.sum(axis=1)), 1.0)
    centroid_of = (incidence.T / 3.0).tocsr()
    projectors = (incidence @ np.einsum("fi,fj->fij", normals, normals).reshape(-1, 9)
                  ).reshape(-1, 3, 3)
    x = mesh.vertices_m.copy()
    for _ in range(iterations):
        plane_offset_m = np.einsum("ij,ij->i", normals, centroid_of @ x)[:, None]
        toward_planes = incidence @ (normals * plane_offset_m) - np.einsum(
            "vij,vj->vi", projectors, x)
        x = x + toward_planes / face_count
    return x
