"""A cache-friendly order for a mesh's vertices and faces, and the way back.

Meshes from the remesher come with their vertices in no spatial order: neighbours sit far apart
in memory, and every sparse product and neighbour gather over them misses the cache. Sorted
along a Morton (Z-order) curve, neighbours are mostly near each other in memory too. The
enhancement runs on the sorted mesh (and hands back the input's order where it keeps the
connectivity); the remesh's angle clean-up runs on it too.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from pipeline.mesh import TriangleMesh
from pipeline.mesh_repair import row_min, stable_argsort

MORTON_BITS = 10
"""Bits per axis of the Morton code: a 1024³ grid over the bounding cube, cells smaller than
an edge on the meshes enhanced here (a 1 m bunny's 5 mm edges span five)."""


@dataclass(frozen=True)
class MeshOrder:
    """A permutation of a mesh's vertices and faces."""

    vertex_order: NDArray[np.int64]
    """(V,) the input index of each vertex in the new order."""
    face_order: NDArray[np.int64]
    """(F,) the input index of each face in the new order."""


def morton_codes(points_m: NDArray[np.float64], bits: int = MORTON_BITS) -> NDArray[np.uint64]:
    """(N,) Z-order codes of (N, 3) points: their cells in a 2^bits grid (bits <= 21) over the
    bounding cube, the cells' coordinate bits interleaved (x lowest)."""
    if len(points_m) == 0:
        return np.zeros(0, dtype=np.uint64)
    # Column by column: numpy reduces an (N, 3) array along its rows 25 times slower.
    columns = [points_m[:, axis] for axis in range(3)]
    low = np.array([c.min() for c in columns])
    span = max(max(float(c.max()) - lo for c, lo in zip(columns, low, strict=True)), 1e-300)
    cells = np.minimum(((points_m - low) / span * 2**bits).astype(np.uint64), 2**bits - 1)
    return (_spread(cells[:, 0]) | (_spread(cells[:, 1]) << np.uint64(1))
            | (_spread(cells[:, 2]) << np.uint64(2)))


_SPREAD_STEPS = ((32, 0x1F00000000FFFF), (16, 0x1F0000FF0000FF), (8, 0x100F00F00F00F00F),
                 (4, 0x10C30C30C30C30C3), (2, 0x1249249249249249))
"""Shifts and masks that move bit b of a 21-bit number to bit 3 b in five steps, where a
loop over the bits took 30."""


def _spread(cells: NDArray[np.uint64]) -> NDArray[np.uint64]:
    """(N,) each of (N,) numbers below 2^21 with two zero bits put after each of its bits."""
    x = cells
    for shift, mask in _SPREAD_STEPS:
        x = (x | (x << np.uint64(shift))) & np.uint64(mask)
    return x


def spatial_order(mesh: TriangleMesh) -> MeshOrder:
    """Vertices along the Morton curve; faces by their first vertex in that order."""
    vertex_order = stable_argsort(morton_codes(mesh.vertices_m))
    new_index = _inverse(vertex_order)
    face_order = stable_argsort(row_min(new_index[mesh.faces]))
    return MeshOrder(vertex_order=vertex_order, face_order=face_order)


def reordered(mesh: TriangleMesh, order: MeshOrder) -> TriangleMesh:
    """The same mesh, colours and normals with it, with its vertices and faces in `order`."""
    new_index = _inverse(order.vertex_order)
    return replace(
        mesh, vertices_m=mesh.vertices_m[order.vertex_order],
        faces=new_index[mesh.faces[order.face_order]].astype(np.int32),
        vertex_colors=_permuted(mesh.vertex_colors, order.vertex_order),
        vertex_normals=_permuted(mesh.vertex_normals, order.vertex_order))


def restored(mesh: TriangleMesh, order: MeshOrder) -> TriangleMesh:
    """A mesh in `order` (as `reordered` made it) back in its input's order."""
    back = _inverse(order.vertex_order)
    faces = np.empty_like(mesh.faces)
    faces[order.face_order] = order.vertex_order[mesh.faces]
    return replace(
        mesh, vertices_m=mesh.vertices_m[back], faces=faces,
        vertex_colors=_permuted(mesh.vertex_colors, back),
        vertex_normals=_permuted(mesh.vertex_normals, back))


def _inverse(permutation: NDArray[np.int64]) -> NDArray[np.int64]:
    inverse = np.empty_like(permutation)
    inverse[permutation] = np.arange(len(permutation))
    return inverse


def _permuted(per_vertex: NDArray | None, permutation: NDArray[np.int64]) -> NDArray | None:
    return None if per_vertex is None else per_vertex[permutation]


def in_spatial_order(vertices_m: NDArray[np.float64], faces: NDArray[np.int32]
                     ) -> tuple[NDArray[np.float64], NDArray[np.int32], NDArray[np.int64]]:
    """A mesh's vertices and faces in `spatial_order`, and (F,) the input index of each face.
    The remesh kernel runs faster on it too (the bunny's enhanced mesh 0.9 -> 0.6 s), and the
    angle clean-up's edge tables and neighbour gathers about twice as fast."""
    mesh = TriangleMesh(vertices_m=vertices_m, faces=faces)
    order = spatial_order(mesh)
    ordered = reordered(mesh, order)
    return ordered.vertices_m, ordered.faces, order.face_order
