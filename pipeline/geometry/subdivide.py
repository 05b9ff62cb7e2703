"""Splitting chosen edges of a triangle mesh at given points (adaptive subdivision).

Each face is cut by the templates of red-green refinement: with one edge split, in two; with
two, a corner triangle and the rest (a quad) across its shorter diagonal; with three, in
four. The mesh stays conforming (a split edge is split in both its faces) and keeps its
orientation.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from pipeline.geometry.repair import edge_table

FloatArray = NDArray[np.float64]
Faces = NDArray[np.int32]


def split_edges(vertices_m: FloatArray, faces: Faces, split: NDArray[np.bool_],
                points_m: FloatArray) -> tuple[FloatArray, Faces]:
    """The mesh with each edge of `edge_table(faces)` where (E,) `split` is set cut at its row
    of (E, 3) `points_m` (rows of edges not split are ignored).

    Returns the vertices (the input's, then one per split edge in edge order) and the faces.
    """
    edges, opposite = edge_table(faces)
    new_vertex = np.full(len(edges), -1, dtype=np.int64)
    new_vertex[split] = len(vertices_m) + np.arange(np.count_nonzero(split))
    vertices = np.vstack([vertices_m, points_m[split]])
    # mid[f, c]: the new vertex on the edge opposite corner c of face f, or -1.
    mid = new_vertex[opposite]
    splits = (mid >= 0).sum(axis=1)
    parts = [faces[splits == 0].astype(np.int64)]
    parts += _one_split(faces[splits == 1], mid[splits == 1])
    parts += _two_splits(vertices, faces[splits == 2], mid[splits == 2])
    parts += _three_splits(faces[splits == 3], mid[splits == 3])
    return vertices, np.vstack(parts).astype(np.int32)


def _rotated(faces: Faces, mid: NDArray[np.int64], first: NDArray[np.int64]
             ) -> tuple[NDArray[np.int64], ...]:
    """Corners and midpoints of each face turned so that corner `first` comes first (the
    faces' orientation kept): v0, v1, v2, m0, m1, m2 with m_i opposite v_i."""
    order = (first[:, None] + np.arange(3)[None, :]) % 3
    v = np.take_along_axis(faces.astype(np.int64), order, axis=1)
    m = np.take_along_axis(mid, order, axis=1)
    return (*v.T, *m.T)


def _one_split(faces: Faces, mid: NDArray[np.int64]) -> list[NDArray[np.int64]]:
    v0, v1, v2, m0, _, _ = _rotated(faces, mid, np.argmax(mid >= 0, axis=1))
    return [np.column_stack([v0, v1, m0]), np.column_stack([v0, m0, v2])]


def _two_splits(vertices_m: FloatArray, faces: Faces, mid: NDArray[np.int64]
                ) -> list[NDArray[np.int64]]:
    # v0 is the corner opposite the edge kept whole: the corner triangle is v0's.
    v0, v1, v2, _, m1, m2 = _rotated(faces, mid, np.argmax(mid < 0, axis=1))
    across_v2 = (np.linalg.norm(vertices_m[m2] - vertices_m[v2], axis=1)
                 <= np.linalg.norm(vertices_m[v1] - vertices_m[m1], axis=1))
    quad_a = [np.column_stack([m2, v1, v2]), np.column_stack([m2, v2, m1])]
    quad_b = [np.column_stack([m2, v1, m1]), np.column_stack([v1, v2, m1])]
    return [np.column_stack([v0, m2, m1]),
            *(np.where(across_v2[:, None], a, b) for a, b in zip(quad_a, quad_b, strict=True))]


def _three_splits(faces: Faces, mid: NDArray[np.int64]) -> list[NDArray[np.int64]]:
    v0, v1, v2 = faces.astype(np.int64).T
    m0, m1, m2 = mid.T
    return [np.column_stack([v0, m2, m1]), np.column_stack([v1, m0, m2]),
            np.column_stack([v2, m1, m0]), np.column_stack([m0, m1, m2])]
