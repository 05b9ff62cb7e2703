"""Mesh checks and repairs that remeshing kernels need: no degenerate or duplicate faces,
manifold edges and vertices, no tiny pieces. Vectorised numpy on (V, 3) / (F, 3) arrays.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from pipeline.geometry.mesh import coordinate_columns_m, face_blocks, face_cross_columns_m2

FloatArray = NDArray[np.float64]
Faces = NDArray[np.int32]


def triangle_angles_deg(vertices_m: FloatArray, faces: Faces) -> FloatArray:
    """(F, 3) interior angle at each corner of each face, degrees (0 for degenerate). On the
    coordinates' columns, as `face_areas` (a third quicker than on gathered (F, 3, 3)
    corners, with the same bits), by `mesh.face_blocks`."""
    columns = coordinate_columns_m(vertices_m)
    angles = np.empty(faces.shape, dtype=np.float64)
    for block in face_blocks(len(faces)):
        _block_angles_deg(columns, faces[block], angles[block])
    return angles


def _block_angles_deg(columns: FloatArray, faces: Faces, out_deg: FloatArray) -> None:
    """`triangle_angles_deg` of (B, 3) `faces` on (3, V) coordinate `columns`, into (B, 3)
    `out_deg`."""
    index = faces.T.astype(np.intp)
    corner = [[axis.take(index[c]) for axis in columns] for c in range(3)]
    # side[c] runs from corner c to corner c + 1; corner c sits between side[c] and the
    # reversed side[c - 1], so each side's length is taken once, not twice.
    side = [[corner[(c + 1) % 3][k] - corner[c][k] for k in range(3)] for c in range(3)]
    length = [np.sqrt(x * x + y * y + z * z) for x, y, z in side]
    for c in range(3):
        (x, y, z), (u, v, w) = side[c], side[c - 1]
        denom = length[c] * length[c - 1]
        # One buffer in turn: the dot product, the cosine, the angle in radians, in degrees.
        cos = x * u
        cos += y * v
        cos += z * w
        np.negative(cos, out=cos)
        positive = denom > 0
        np.divide(cos, denom, out=cos, where=positive)
        cos[~positive] = 1.0
        np.clip(cos, -1.0, 1.0, out=cos)
        out_deg[:, c] = np.degrees(np.arccos(cos, out=cos), out=cos)


DEGENERATE_AREA_M2 = 1e-14
"""`repair` removes faces of this area or less."""


def row_min(values: NDArray) -> NDArray:
    """(F,) each row's smallest of (F, 3): four times as fast as a reduction along the rows."""
    return np.minimum(np.minimum(values[:, 0], values[:, 1]), values[:, 2])


def row_max(values: NDArray) -> NDArray:
    """(F,) each row's largest of (F, 3)."""
    return np.maximum(np.maximum(values[:, 0], values[:, 1]), values[:, 2])


def stable_sort(keys: NDArray[np.integer]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """The non-negative integer `keys` sorted, and (N,) the order that sorts them, ties in
    index order: the order of ``np.argsort(keys, kind="stable")``. Where a key and its index
    fit together in 63 bits they are packed into one int64 and sorted plainly, which numpy
    does with its SIMD sort, about five times as fast as its stable argsort; larger keys take
    the stable argsort."""
    count = len(keys)
    index_bits = max(1, (count - 1).bit_length())
    if count == 0 or keys.min() < 0 or int(keys.max()).bit_length() + index_bits > 63:
        order = np.argsort(keys, kind="stable")
        return keys[order].astype(np.int64), order
    packed = (keys.astype(np.int64) << index_bits) | np.arange(count, dtype=np.int64)
    packed.sort()
    return packed >> index_bits, packed & ((1 << index_bits) - 1)


def stable_argsort(keys: NDArray[np.integer]) -> NDArray[np.int64]:
    """(N,) `stable_sort`'s order alone."""
    return stable_sort(keys)[1]


def face_areas(vertices_m: FloatArray, faces: Faces) -> FloatArray:
    """(F,) triangle areas, square metres; by `mesh.face_blocks`."""
    columns = coordinate_columns_m(vertices_m)
    areas = np.empty(len(faces))
    for block in face_blocks(len(faces)):
        x, y, z = face_cross_columns_m2(columns, faces[block])
        areas[block] = 0.5 * np.sqrt(x * x + y * y + z * z)
    return areas


def edge_table(faces: Faces) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Undirected edges (E, 2) sorted per row, and (F, 3) the edge opposite each corner."""
    a = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0]]).astype(np.int64)
    b = np.concatenate([faces[:, 2], faces[:, 0], faces[:, 1]]).astype(np.int64)
    low, high = np.minimum(a, b), np.maximum(a, b)
    span = int(high.max(initial=0)) + 1
    # np.unique by hand, with a stable sort, so that equal edges keep the order of the faces.
    sorted_keys, order = stable_sort(low * span + high)
    first = np.ones(len(order), dtype=bool)
    first[1:] = sorted_keys[1:] != sorted_keys[:-1]
    inverse = np.empty(len(order), dtype=np.int64)
    inverse[order] = np.cumsum(first) - 1
    kept_low, kept_high = np.divmod(sorted_keys[first], span)
    return np.column_stack([kept_low, kept_high]), inverse.reshape(3, -1).T


def faces_at(faces: Faces, at_vertex: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """(F,) the faces with a corner where (V,) `at_vertex` is set: three column gathers, a
    third of the time of a reduction over (F, 3) gathered rows."""
    return at_vertex[faces[:, 0]] | at_vertex[faces[:, 1]] | at_vertex[faces[:, 2]]


def grown_by_rings(faces: Faces, at_vertex: NDArray[np.bool_], rings: int
                   ) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """(V,) `at_vertex` grown by `rings` rings of faces (each ring adds the corners of every
    face with a corner in it), and (F,) the faces with a corner in the grown set. The index
    columns are converted to numpy's index type once: a gather converts int32 indices on every
    call."""
    columns = [faces[:, c].astype(np.intp) for c in range(3)]
    near = at_vertex.copy()
    for _ in range(rings):
        near[faces[near[columns[0]] | near[columns[1]] | near[columns[2]]].ravel()] = True
    return near, near[columns[0]] | near[columns[1]] | near[columns[2]]


def faces_per_edge(opposite: NDArray[np.int64], edge_count: int) -> NDArray[np.int64]:
    """(E,) how many faces use each edge, from `edge_table`'s (F, 3) opposite-edge table:
    1 on the boundary, 2 inside, more where the mesh is non-manifold."""
    return np.bincount(opposite.ravel(), minlength=edge_count)


def compact(vertices_m: FloatArray, faces: Faces) -> tuple[FloatArray, Faces]:
    """Drop unreferenced vertices and renumber faces."""
    used, renumbered = used_vertices(faces, len(vertices_m))
    return vertices_m[used], renumbered


def used_vertices(faces: NDArray[np.integer], vertex_count: int
                  ) -> tuple[NDArray[np.int64], Faces]:
    """(U,) ascending, the vertices `faces` use, and the faces renumbered onto them:
    ``np.unique(faces, return_inverse=True)`` by marking the used vertices, with no sort."""
    used = np.zeros(vertex_count, dtype=bool)
    used[faces.ravel()] = True
    # int32 from the start: the faces gather it as they are (no int64 copy to convert).
    new_index = np.cumsum(used, dtype=np.int32) - 1
    return np.flatnonzero(used), new_index[faces]


RUN_COPY_MAX_DROPPED = 256
"""`without_rows` copies the runs between at most this many dropped rows; past it, a mask.
Each run is a slice in Python (about a microsecond), so the runs cost far less than a mask of
every row up to thousands of drops on a mesh of a few hundred thousand faces; a clean-up drops a
few dozen."""


def without_rows(array: NDArray, dropped: NDArray[np.int64]) -> NDArray:
    """`array` less its rows `dropped` (ascending, distinct). The few rows a clean-up drops
    are cut out by copying the runs between them, a tenth of the time of a mask of every
    row."""
    if len(dropped) > RUN_COPY_MAX_DROPPED:
        keep = np.ones(len(array), dtype=bool)
        keep[dropped] = False
        return array[keep]
    starts, stops = [0, *(dropped + 1).tolist()], [*dropped.tolist(), len(array)]
    return np.concatenate([array[a:b] for a, b in zip(starts, stops, strict=True)])


def faces_sharing_vertices(faces: Faces, vertex_count: int):
    """(F, F) scipy CSR matrix: entry (f, g) counts the vertices faces f and g share (the
    diagonal, a face with itself, included)."""
    from scipy.sparse import coo_matrix

    rows = np.repeat(np.arange(len(faces)), 3)
    incidence = coo_matrix((np.ones(len(rows)), (rows, faces.ravel())),
                           shape=(len(faces), vertex_count)).tocsr()
    return incidence @ incidence.T


def face_components(faces: Faces, vertex_count: int) -> NDArray[np.int64]:
    """(F,) connected-component label of each face (faces sharing a vertex are connected)."""
    from scipy.sparse.csgraph import connected_components

    _, labels = connected_components(faces_sharing_vertices(faces, vertex_count),
                                     directed=False)
    return np.asarray(labels, dtype=np.int64)


def drop_small_components(vertices_m: FloatArray, faces: Faces, min_share: float
                          ) -> tuple[FloatArray, Faces]:
    """Remove connected pieces with fewer faces than min_share of the largest piece's."""
    if len(faces) == 0:
        return vertices_m, faces
    labels = face_components(faces, len(vertices_m))
    sizes = np.bincount(labels)
    return compact(vertices_m, faces[sizes[labels] >= min_share * sizes.max()])


def non_manifold_vertices(faces: Faces, vertex_count: int,
                          edges: NDArray[np.int64] | None = None) -> NDArray[np.bool_]:
    """(V,) vertices whose faces form more than one fan (open bow-ties and the like);
    `edges`: the faces' `edge_table` edges, where already known.

    Around a vertex with one fan, incident edges number faces (closed) or faces + 1 (open).
    """
    if edges is None:
        edges, _ = edge_table(faces)
    edge_count = np.bincount(edges.ravel(), minlength=vertex_count)
    face_count = np.bincount(faces.ravel(), minlength=vertex_count)
    return (edge_count - face_count) > 1


def _first_of_each_corner_set(faces: NDArray[np.integer]) -> NDArray[np.int64]:
    """(U,) ascending, the first face of each set of faces with the same three corners: the
    faces' sorted corners ordered as ``np.lexsort`` would, by two stable sorts (the largest
    corner, then the two smaller ones as one key), each of `stable_argsort`'s packed keys."""
    low, high = row_min(faces).astype(np.int64), row_max(faces).astype(np.int64)
    middle = faces.sum(axis=1, dtype=np.int64) - low - high
    order = stable_argsort(high)
    order = order[stable_argsort((low * (int(high.max(initial=0)) + 1) + middle)[order])]
    corners = np.column_stack([low, middle, high])[order]
    first = np.ones(len(faces), dtype=bool)
    first[1:] = np.any(corners[1:] != corners[:-1], axis=1)
    return np.sort(order[first])


def repair(vertices_m: FloatArray, faces: Faces, min_component_share: float = 0.0,
           rounds: int = 4) -> tuple[FloatArray, Faces, dict[str, int]]:
    """A mesh a remeshing kernel can take: degenerate and duplicate faces removed, faces on
    non-manifold edges and around non-manifold vertices removed, small pieces dropped.

    Returns the repaired (V, 3), (F, 3) and counts of what was removed.
    """
    vertices = np.asarray(vertices_m, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces: expected (F, 3), got {faces.shape}")
    if len(faces) and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise ValueError("faces: index out of range of vertices_m")
    if not np.all(np.isfinite(vertices)):
        raise ValueError("vertices_m: not all finite")
    removed = {"degenerate": 0, "duplicate": 0, "non_manifold": 0}
    distinct = ((faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2])
                & (faces[:, 2] != faces[:, 0]))
    area_ok = face_areas(vertices, faces.astype(np.int32)) > DEGENERATE_AREA_M2
    removed["degenerate"] = int(np.sum(~(distinct & area_ok)))
    faces = faces[distinct & area_ok]
    first = _first_of_each_corner_set(faces)
    removed["duplicate"] = len(faces) - len(first)
    faces = faces[first]
    for _ in range(rounds):
        faces32 = faces.astype(np.int32)
        edges, opposite = edge_table(faces32)
        uses = faces_per_edge(opposite, len(edges))
        bad_face = (uses[opposite] > 2).any(axis=1)
        bad_face |= faces_at(faces, non_manifold_vertices(faces32, len(vertices), edges))
        if not bad_face.any():
            break
        removed["non_manifold"] += int(bad_face.sum())
        faces = faces[~bad_face]
    out_v, out_f = compact(vertices, faces.astype(np.int32))
    if min_component_share > 0:
        out_v, out_f = drop_small_components(out_v, out_f, min_component_share)
    return out_v, out_f, removed


def is_repaired(vertices_m: FloatArray, faces: Faces) -> bool:
    """Whether `repair` (with no small pieces dropped) leaves the mesh as it is. What it
    checks is the faces' topology but for the degenerate faces' areas, so a mesh whose
    vertices then move needs only `face_areas` checked again."""
    out_vertices, out_faces, removed = repair(vertices_m, faces)
    return len(out_vertices) == len(vertices_m) and not any(removed.values())
