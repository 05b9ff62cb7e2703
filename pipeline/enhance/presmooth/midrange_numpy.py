"""The midrange estimator's refinement in numpy and scipy on the host (`midrange` chooses this
or `midrange_torch`): the neighbourhoods' ranges are row reductions over the closed one-ring."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from pipeline.enhance.presmooth.midrange_common import BoundedNoiseConfig, residual_kurtosis
from pipeline.geometry.mesh import TriangleMesh, vertex_normals
from pipeline.geometry.smoothing import adjacency


def refined(noisy: TriangleMesh, smooth: TriangleMesh, config: BoundedNoiseConfig
            ) -> TriangleMesh | None:
    """`midrange.refined_where_bounded(noisy, smooth, config)` (`config.rings` > 0)."""
    normals = vertex_normals(smooth.vertices_m, smooth.faces).astype(np.float64)
    residual_m = np.sum((noisy.vertices_m - smooth.vertices_m) * normals, axis=1)
    if residual_kurtosis(residual_m) >= config.max_kurtosis:
        return None
    closed = closed_neighbourhoods(smooth.faces, smooth.vertex_count)
    low_m, high_m = neighbourhood_range(residual_m, closed, config.rings)
    middle_m = 0.5 * (low_m + high_m)
    mean_closed = sp.diags(1.0 / np.diff(closed.indptr)) @ closed
    for _ in range(config.smoothing):
        middle_m = mean_closed @ middle_m
    return smooth.with_vertices(smooth.vertices_m + normals * middle_m[:, None])


def closed_neighbourhoods(faces: NDArray[np.int32], vertex_count: int) -> sp.csr_matrix:
    """(V, V) 0/1 pattern of each vertex and its neighbours (the closed one-ring), rows sorted."""
    closed = (adjacency(faces, vertex_count) + sp.identity(vertex_count)).tocsr()
    closed.sort_indices()
    closed.data[:] = 1.0
    return closed


def neighbourhood_range(values: NDArray[np.float64], closed: sp.csr_matrix, rings: int
                        ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """((V,), (V,)) the least and greatest of `values` within `rings` rings of each vertex;
    `closed` is `closed_neighbourhoods` (every row holds its vertex, so none is empty)."""
    low, high = values, values
    for _ in range(rings):
        low = np.minimum.reduceat(low[closed.indices], closed.indptr[:-1])
        high = np.maximum.reduceat(high[closed.indices], closed.indptr[:-1])
    return low, high
