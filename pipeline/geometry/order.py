"""A cache-friendly order for a mesh's vertices and faces, and the way back.

Meshes from the remesher come with their vertices in no spatial order: neighbours sit far apart
in memory, and every sparse product and neighbour gather over them misses the cache. Sorted
along a Morton (Z-order) curve, neighbours are mostly near each other in memory too. The
enhancement runs on the sorted mesh (and hands back the input's order where it keeps the
connectivity); the remesh's angle clean-up runs on it too.

The order is canonical: it depends on the surface, not on how its file listed it. Vertices
that share a Morton cell are ordered by finer cells, then by their coordinates; each face
starts at its least vertex, and faces are sorted by all three. So a mesh whose vertices or
faces are listed in another order, or whose faces start at another corner, comes out as
the same arrays, and everything computed on them (sums, normals, the remesh's decisions)
is the same bit for bit. Only vertices at exactly the same point keep their input order
(docs/decisions/canonical-mesh-order.md).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from pipeline.geometry.mesh import TriangleMesh

MORTON_BITS = 10
"""Bits per axis of the Morton code: a 1024³ grid over the bounding cube, cells smaller than
an edge on the meshes enhanced here (a 1 m bunny's 5 mm edges span five)."""
ORDER_BITS = 21
"""Bits per axis of the codes vertices are sorted by: the most that fit in 63 bits. The cells
nest, so a code's top 3 × `MORTON_BITS` bits are its coarse code: the order along the coarse
curve is kept, and vertices sharing a coarse cell, which it leaves in the input's order, are
put in order by finer cells."""


@dataclass(frozen=True)
class MeshOrder:
    """A permutation of a mesh's vertices and faces."""

    vertex_order: NDArray[np.int64]
    """(V,) the input index of each vertex in the new order."""
    face_order: NDArray[np.int64]
    """(F,) the input index of each face in the new order."""
    face_start: NDArray[np.int64] | None = None
    """(F,) in the new order, the corner (0-2) of its input face each face starts at, its
    winding kept; None: every face starts at its input's first corner."""


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
"""Shifts and masks that move bit b of a 21-bit number to bit 3 b in five steps rather than a
loop over the bits."""


def _spread(cells: NDArray[np.uint64]) -> NDArray[np.uint64]:
    """(N,) each of (N,) numbers below 2^21 with two zero bits put after each of its bits."""
    x = cells
    for shift, mask in _SPREAD_STEPS:
        x = (x | (x << np.uint64(shift))) & np.uint64(mask)
    return x


def spatial_order(mesh: TriangleMesh) -> MeshOrder:
    """The canonical order (module docstring): vertices along the Morton curve, faces by
    their vertices in that order, each starting at its least."""
    vertex_order = _vertex_order(mesh.vertices_m)
    corners = _inverse(vertex_order)[mesh.faces]
    face_order, face_start = _face_order(corners, len(vertex_order))
    return MeshOrder(vertex_order=vertex_order, face_order=face_order,
                     face_start=face_start[face_order])


def _vertex_order(vertices_m: NDArray[np.float64]) -> NDArray[np.int64]:
    """(V,) vertices by their `ORDER_BITS` Morton codes, ties by x, y and z."""
    codes = morton_codes(vertices_m, ORDER_BITS)
    # Stable: timsort runs on vertices already near their order (a remeshed or split mesh
    # from one in this order) far quicker than a quicksort, and no slower on others.
    order = np.argsort(codes, kind="stable")
    if np.any(codes[order[1:]] == codes[order[:-1]]):
        order = np.lexsort((vertices_m[:, 2], vertices_m[:, 1], vertices_m[:, 0], codes))
    return order.astype(np.int64)


def _face_order(corners: NDArray[np.int64], vertex_count: int
                ) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """(F,) faces, as (F, 3) vertex indices in the new order, sorted by their least rotation,
    and (F,) the corner each face's least rotation starts at. Equal rotations are the same
    face, so their order among themselves changes nothing. Past 2^21 vertices the three
    indices do not fit one key: faces start at their least vertex and are sorted by three
    keys, and a face with a repeated vertex may start at either of its two."""
    bits = max(1, (vertex_count - 1).bit_length())
    if 3 * bits > 63:
        start = np.argmin(corners, axis=1)
        rows = _rotated(corners, start)
        return np.lexsort((rows[:, 2], rows[:, 1], rows[:, 0])).astype(np.int64), start
    a, b, c = (np.ascontiguousarray(corners[:, i]) for i in range(3))
    from_a = (a << (2 * bits)) | (b << bits) | c
    from_b = (b << (2 * bits)) | (c << bits) | a
    from_c = (c << (2 * bits)) | (a << bits) | b
    keys = np.minimum(np.minimum(from_a, from_b), from_c)
    start = np.where(keys == from_a, 0, np.where(keys == from_b, 1, 2))
    # Stable: timsort runs on faces already near their order, quicker than a quicksort.
    return np.argsort(keys, kind="stable"), start


def _rotated(faces: NDArray, start: NDArray[np.int64]) -> NDArray:
    """(F, 3) each row of `faces` rotated to begin at its corner `start`: the same triangle,
    the same winding. Column by column: quicker than a gather of the rows' corners."""
    a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
    one, two = start == 1, start == 2
    out = np.empty_like(faces)
    out[:, 0] = np.where(one, b, np.where(two, c, a))
    out[:, 1] = np.where(one, c, np.where(two, a, b))
    out[:, 2] = np.where(one, a, np.where(two, b, c))
    return out


def reordered(mesh: TriangleMesh, order: MeshOrder) -> TriangleMesh:
    """The same mesh, colours and normals with it, with its vertices and faces in `order`."""
    faces = mesh.faces[order.face_order]
    if order.face_start is not None:
        faces = _rotated(faces, order.face_start)
    return replace(
        mesh, vertices_m=mesh.vertices_m[order.vertex_order],
        faces=_inverse(order.vertex_order).astype(np.int32)[faces],
        vertex_colors=_permuted(mesh.vertex_colors, order.vertex_order),
        vertex_normals=_permuted(mesh.vertex_normals, order.vertex_order))


def restored(mesh: TriangleMesh, order: MeshOrder) -> TriangleMesh:
    """A mesh in `order` (as `reordered` made it) back in its input's order."""
    back = _inverse(order.vertex_order)
    in_order = order.vertex_order[mesh.faces]
    if order.face_start is not None:
        in_order = _rotated(in_order, (3 - order.face_start) % 3)
    faces = np.empty_like(mesh.faces)
    faces[order.face_order] = in_order
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
                     ) -> tuple[NDArray[np.float64], NDArray[np.int32], MeshOrder]:
    """A mesh's vertices and faces in `spatial_order`, and the order (for per-face values:
    `corners_reordered`). The remesh kernel runs faster on it too, and the angle clean-up's
    edge tables and neighbour gathers about twice as fast."""
    mesh = TriangleMesh(vertices_m=vertices_m, faces=faces)
    order = spatial_order(mesh)
    ordered = reordered(mesh, order)
    return ordered.vertices_m, ordered.faces, order


def corners_reordered(per_corner: NDArray, order: MeshOrder) -> NDArray:
    """(F, 3) values at each face's corners (its angles) moved with the faces to `order`."""
    moved = per_corner[order.face_order]
    return moved if order.face_start is None else _rotated(moved, order.face_start)
