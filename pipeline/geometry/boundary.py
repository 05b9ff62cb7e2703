"""Open boundaries under umbrella smoothing.

A boundary vertex's neighbours all lie on one side of it, so each smoothing step pulls it
inwards along the surface by a fraction of an edge, and long smoothing lets an open boundary
retract by several millimetres. That one-sided offset is the shape of the mesh there, not
noise, so it is measured once, on a pilot, and left out of every step
(`scale_selection_numpy.field_ops`); the vertex still follows its noise along the surface,
along the boundary and along the normal.

The pilot has itself retracted a little, so the offset comes out short and about a quarter of
the retraction is held back on a regular grid (tests). A pilot held against retraction would
hold all of it but keep the boundary's noise in the surface, so it is not used.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from pipeline.geometry.mesh import TriangleMesh, vertex_normals
from pipeline.geometry.repair import edge_table, faces_per_edge
from pipeline.geometry.smoothing import twice_field


def boundary_half_edges(faces: NDArray[np.int32]) -> NDArray[np.int64]:
    """(B, 2) the directed edges, in their face's winding, that only one face uses."""
    edges, opposite = edge_table(faces)
    on_boundary = faces_per_edge(opposite, len(edges))[opposite] == 1
    # edge_table's opposite edge of corner c runs from corner c + 1 to corner c + 2.
    half_edges = np.stack([np.roll(faces, -1, axis=1), np.roll(faces, -2, axis=1)], axis=2)
    return half_edges[on_boundary].astype(np.int64)


def across_boundary(vertices_m: NDArray[np.float64], faces: NDArray[np.int32],
                    half: NDArray[np.int64]) -> NDArray[np.float64]:
    """(V, 3) at each boundary vertex the unit direction in the surface across the boundary
    (normal x boundary tangent; its sign does not matter to its users); zero elsewhere.
    `half` are the faces' `boundary_half_edges`."""
    tangent = np.zeros_like(vertices_m)
    along = vertices_m[half[:, 1]] - vertices_m[half[:, 0]]
    for end in (0, 1):
        np.add.at(tangent, half[:, end], along)
    across = np.cross(vertex_normals(vertices_m, faces).astype(np.float64), tangent)
    length = np.linalg.norm(across, axis=1, keepdims=True)
    return np.divide(across, length, out=np.zeros_like(across), where=length > 0)


def boundary_offset(mesh: TriangleMesh, mean_op: sp.csr_matrix, pilot_iterations: int
                    ) -> NDArray[np.float64] | None:
    """(V, 3) the umbrella offset (mean of neighbours minus the vertex) across the boundary,
    measured on the mesh after `pilot_iterations` Laplacian steps (the noise would swamp it
    on the mesh itself), zero away from the boundary; None for a closed mesh, or where
    `pilot_iterations` is 0 (the boundary is smoothed like the rest). `mean_op` is the mesh's
    `smoothing.mean_operator`."""
    if pilot_iterations == 0:
        return None
    half = boundary_half_edges(mesh.faces)
    if len(half) == 0:
        return None
    pilot = twice_field(mean_op, mesh.vertices_m, pilot_iterations, 1, 0.5)
    across = across_boundary(pilot, mesh.faces, half)
    offset = np.sum((mean_op @ pilot - pilot) * across, axis=1, keepdims=True)
    return offset * across
