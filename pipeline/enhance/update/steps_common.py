"""The update's settings and the per-view steps it averages: what both implementations of the
mesh update (`steps_numpy` on the host, `steps_torch` on a device) take and give."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray


@dataclass(frozen=True)
class UpdateConfig:
    """How vertices follow the enhanced depth.

    A vertex moves by the enhanced depth's change from the mesh's own render at its pixel,
    not to the enhanced depth itself: the render, looked up between pixels, is not exactly
    the vertex's depth, so only the enhancer's correction is carried. Vertices no view sees
    take the smooth interpolation of their seen neighbours' moves, which keeps the hidden
    parts of an already smooth (pre-smoothed) mesh where they are."""

    max_step_fraction: float = 0.03
    """Largest vertex move, as a fraction of the bounding-sphere radius."""
    min_cos: float = 0.15
    """A view sees a vertex only if cos(angle between its normal and the view ray) is above this."""
    tolerance_px: float = 1.0
    """Depth-test tolerance in pixel sizes (widened on slanted surfaces)."""
    unseen_iterations: int = 60
    """Smoothing iterations of the unseen vertices' moves (seen vertices' moves held fixed)."""
    normal_smoothing: int = 2
    """Neighbour-averaging passes over vertex normals before visibility (noisy normals)."""


@dataclass(frozen=True)
class ViewSteps:
    """Where each view's enhanced depth would move each vertex, before the views are averaged."""

    steps_m: NDArray[np.float64]
    """(K, V) signed step along view k's forward axis (0 where view k does not see the vertex)."""
    weights: NDArray[np.float64]
    """(K, V) view k's weight for the vertex: cos² of its normal to the ray where the view
    sees it (depth test, facing, a step under the cap), else 0."""
    forwards: NDArray[np.float64]
    """(K, 3) the views' forward axes."""
    normals: NDArray[np.float64]
    """(V, 3) the (neighbour-averaged) unit vertex normals the visibility was judged with."""
    cap_m: float
    """Largest move of a vertex."""
    mean_op: sp.csr_matrix
    """(V, V) the mesh's neighbour-mean operator, which the normals were smoothed with and the
    unseen vertices are smoothed with (built once for both)."""

    def along_normals_m(self) -> NDArray[np.float64]:
        """(K, V) each view's step projected onto the vertex normal."""
        return self.steps_m * (self.forwards @ self.normals.T)

    @property
    def seen(self) -> NDArray[np.bool_]:
        """(V,) vertices at least one view sees."""
        return self.weights.sum(axis=0) > 0
