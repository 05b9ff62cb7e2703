"""The midrange estimator's refinement in torch on a device, float64 (`midrange` chooses this
or `midrange_numpy`): the neighbourhoods' ranges are scatter reductions over `mesh_torch`'s
neighbour pattern."""

from __future__ import annotations

import numpy as np
import torch

from pipeline.enhance import mesh_torch
from pipeline.enhance.device import csr_tensor, on_device
from pipeline.enhance.presmooth.midrange_common import BoundedNoiseConfig, residual_kurtosis
from pipeline.enhance.presmooth.scale_selection_common import along
from pipeline.geometry.mesh import TriangleMesh


def refined(noisy: TriangleMesh, smooth: TriangleMesh, config: BoundedNoiseConfig,
            device: str) -> TriangleMesh | None:
    """`midrange.refined_where_bounded(noisy, smooth, config)` (`config.rings` > 0) on
    `device`."""
    faces = on_device(smooth.faces.astype(np.int64), device)
    smooth_m = on_device(smooth.vertices_m, device)
    normals = mesh_torch.vertex_normals(smooth_m, faces).double()
    residual_m = along(on_device(noisy.vertices_m, device) - smooth_m, normals)
    if residual_kurtosis(residual_m) >= config.max_kurtosis:
        return None
    pattern = mesh_torch.neighbour_pattern(faces, smooth.vertex_count)
    low_m, high_m = neighbourhood_range(residual_m, pattern, config.rings)
    middle_m = 0.5 * (low_m + high_m)
    mean_closed = closed_mean(pattern)
    for _ in range(config.smoothing):
        middle_m = mean_closed @ middle_m
    return smooth.with_vertices((smooth_m + normals * middle_m[:, None]).cpu().numpy())


def neighbourhood_range(values: torch.Tensor, pattern: mesh_torch.NeighbourPattern,
                        rings: int) -> tuple[torch.Tensor, torch.Tensor]:
    """((V,), (V,)) the least and greatest of (V,) `values` within `rings` rings of each
    vertex (every vertex is in its own closed one-ring)."""
    low, high = values, values
    for _ in range(rings):
        low = values.new_empty(len(values)).scatter_reduce_(
            0, pattern.rows, low[pattern.columns], "amin", include_self=False)
        high = values.new_empty(len(values)).scatter_reduce_(
            0, pattern.rows, high[pattern.columns], "amax", include_self=False)
    return low, high


def closed_mean(pattern: mesh_torch.NeighbourPattern) -> torch.Tensor:
    """(V, V) sparse CSR float64: row i averages i and its neighbours."""
    count = pattern.vertex_count
    values = (1.0 / (pattern.neighbour_count + 1).to(torch.float64))[pattern.rows]
    return csr_tensor(*mesh_torch.csr_rows(pattern.rows, pattern.columns, count), values,
                      (count, count))
