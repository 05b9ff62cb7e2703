"""The twicings' smoothing steps (`FieldOps`) in scipy and numpy on the host
(`scale_selection` chooses these or `scale_selection_torch`'s)."""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from pipeline.enhance.presmooth.scale_selection_common import FieldOps, leaving_out
from pipeline.geometry.boundary import boundary_offset
from pipeline.geometry.mesh import TriangleMesh, vertex_normals
from pipeline.geometry.smoothing import mean_operator


def mesh_field_ops(mesh: TriangleMesh, boundary_pilot_iterations: int) -> FieldOps:
    """The mesh's `FieldOps` on the host, steps leaving out the boundary offset measured
    after `boundary_pilot_iterations` steps (0: none)."""
    m = mean_operator(mesh.faces, mesh.vertex_count)
    return field_ops(m, mesh.faces, boundary_offset(mesh, m, boundary_pilot_iterations))


def field_ops(mean_op: sp.csr_matrix, faces: NDArray[np.int32],
              offset_m: NDArray[np.float64] | None = None) -> FieldOps:
    """scipy and numpy on the host; `offset_m` (V, 3) is the c that steps leave out
    (`pipeline.geometry.boundary.boundary_offset`); None: zero."""
    mean32 = mean_op.astype(np.float32)
    return FieldOps(
        step=leaving_out(lambda y: y + 0.5 * (mean_op @ y - y), offset_m, _same),
        average=lambda y: mean32 @ y, to_field=_same, to_numpy=_same,
        mean=lambda y: mean_op @ y,
        normals=lambda y: vertex_normals(y, faces).astype(np.float64),
        columns=lambda columns: np.stack(columns, axis=1).astype(np.float32))


def _same(x: Any) -> Any:
    return x
