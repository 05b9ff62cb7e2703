"""Long edges at an open boundary bisected before remeshing (`split_boundary_edges`).

A remeshing kernel that holds the boundary (remesh_botsch) neither splits these edges nor
collapses them, so a coarse mesh's boundary vertices stay hubs of long fans (hundreds of
neighbours, edges tens of target lengths long).
Longest-edge bisection (Rivara): a face is only ever cut across its longest edge, so its
pieces do not become ever thinner.

Every round needs the edge table of the faces it may cut, and a mesh of a few hundred thousand
faces typically has a few dozen long boundary edges, so the rounds run on the faces near the
long edges (`REGION_RINGS`) rather than over the whole mesh, with the same result.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from pipeline.geometry.repair import edge_table, faces_per_edge, grown_by_rings

FloatArray = NDArray[np.float64]
Faces = NDArray[np.int32]

REGION_RINGS = 6
"""Rings of faces around the long boundary edges that the rounds run on. A chain of splits
that reaches the region's rim sends the rounds to the whole mesh."""


def split_boundary_edges(vertices_m: FloatArray, faces: Faces, target_edge_m: float
                         ) -> tuple[FloatArray, Faces]:
    """Edges longer than 4/3 of `target_edge_m` with an end on the boundary bisected, in
    rounds, until there are none; faces with a repeated corner are left alone. The old
    vertices keep their index and the midpoints follow; the faces no round cuts keep their
    order and the pieces of those it cuts follow."""
    v, f, _ = split_boundary_edges_with_parents(vertices_m, faces, target_edge_m)
    return v, f


def split_boundary_edges_with_parents(
    vertices_m: FloatArray, faces: Faces, target_edge_m: float,
    table: tuple[NDArray[np.int64], NDArray[np.int64]] | None = None,
) -> tuple[FloatArray, Faces, NDArray[np.int64]]:
    """`split_boundary_edges`, and (N, 2) the ends of the edge each of the N midpoints
    bisected (output indices; a midpoint's ends come before it). `table`: the faces'
    `edge_table`, where it was made beforehand (it is most of the time here)."""
    v, f = np.asarray(vertices_m, np.float64), np.asarray(faces, np.int32)
    edges, opposite = edge_table(f) if table is None else table
    boundary_edges = edges[faces_per_edge(opposite, len(edges)) == 1]
    on_boundary = np.zeros(len(v), dtype=bool)
    on_boundary[boundary_edges.ravel()] = True
    touching = edges[on_boundary[edges[:, 0]] | on_boundary[edges[:, 1]]]
    length_m = np.linalg.norm(v[touching[:, 0]] - v[touching[:, 1]], axis=1)
    wanted = touching[length_m > target_edge_m * 4 / 3]
    if len(wanted) == 0:
        return v, f, np.zeros((0, 2), dtype=np.int64)
    region = np.flatnonzero(_faces_near(f, wanted, len(v), REGION_RINGS))
    split = _split_in_region(v, f, region, boundary_edges, on_boundary, target_edge_m)
    return split if split is not None else _split_all(v, f, target_edge_m)


def split_everywhere(vertices_m: FloatArray, faces: Faces, target_edge_m: float
                     ) -> tuple[FloatArray, Faces]:
    """`split_boundary_edges` with its rounds over every face: where a chain reaches the
    region's rim, and the reference its region is held equal to."""
    v, f, _ = _split_all(vertices_m, faces, target_edge_m)
    return v, f


def _split_all(vertices_m: FloatArray, faces: Faces, target_edge_m: float
               ) -> tuple[FloatArray, Faces, NDArray[np.int64]]:
    """`split_everywhere`, with the midpoints' parents."""
    v, f = np.asarray(vertices_m, np.float64), np.asarray(faces, np.int32)
    edges, opposite = edge_table(f)
    on_boundary = np.zeros(len(v), dtype=bool)
    on_boundary[edges[faces_per_edge(opposite, len(edges)) == 1].ravel()] = True
    whole = split_rounds(v, f, on_boundary, np.zeros((0, 2), np.int64), target_edge_m)
    assert whole is not None  # with no rim, no round can reach one
    return whole[0], whole[1], whole[3]


def _faces_near(faces: Faces, seed_edges: NDArray[np.int64], vertex_count: int, rings: int
                ) -> NDArray[np.bool_]:
    """(F,) the faces within `rings` rings of faces around the ends of `seed_edges`."""
    near_vertex = np.zeros(vertex_count, dtype=bool)
    near_vertex[seed_edges.ravel()] = True
    return grown_by_rings(faces, near_vertex, rings)[1]


def _split_in_region(v: FloatArray, f: Faces, region: NDArray[np.int64],
                     boundary_edges: NDArray[np.int64], on_boundary: NDArray[np.bool_],
                     target_edge_m: float
                     ) -> tuple[FloatArray, Faces, NDArray[np.int64]] | None:
    """`split_rounds` on the faces `region` alone, joined back into the whole mesh as the
    rounds on the whole would have left it; None where a chain reaches the region's rim.

    The region's vertices keep the whole's order (so equal lengths break the same way) and
    the whole's boundary flags (`boundary_edges`, `on_boundary`); its rim, the edges one of
    its faces uses that are not on the whole's boundary, is never split."""
    used, local = np.unique(f[region], return_inverse=True)
    local_faces = local.reshape(-1, 3).astype(np.int32)
    edges, opposite = edge_table(local_faces)
    one_face = faces_per_edge(opposite, len(edges)) == 1
    rim = edges[one_face & ~_rows_in(used[edges], boundary_edges)]
    split = split_rounds(v[used], local_faces, on_boundary[used], rim, target_edge_m)
    if split is None:
        return None
    local_v, local_f, origin, local_parents = split
    to_whole = np.concatenate([used, len(v) + np.arange(len(local_v) - len(used))])
    uncut = np.ones(len(f), dtype=bool)
    uncut[region] = False
    uncut[region[origin[origin >= 0]]] = True
    pieces = to_whole[local_f[origin < 0]].astype(np.int32)
    return (np.vstack([v, local_v[len(used):]]), np.vstack([f[uncut], pieces]),
            to_whole[local_parents])


def _rows_in(rows: NDArray[np.integer], table: NDArray[np.integer]) -> NDArray[np.bool_]:
    """(N,) whether each of (N, 2) vertex pairs `rows` is a row of (M, 2) `table`."""
    def keys(pairs: NDArray) -> NDArray[np.int64]:
        pairs = pairs.astype(np.int64)
        return (pairs[:, 0] << 32) + pairs[:, 1]

    return np.isin(keys(rows), keys(table))


def split_rounds(v: FloatArray, f: Faces, on_boundary: NDArray[np.bool_],
                 rim: NDArray[np.int64], target_edge_m: float
                 ) -> tuple[FloatArray, Faces, NDArray[np.int64], NDArray[np.int64]] | None:
    """The rounds of `split_boundary_edges` on `f`, given (V,) which of its vertices are on
    the boundary (a midpoint is where its edge is) and (R, 2) `rim` edges (sorted rows)
    that one face uses but are not boundary; None where a round would split one of them.
    Returns the vertices, the faces (those no round cut first, in order, then the pieces),
    (F',) each face's row in `f` (-1: a piece) and (N, 2) the ends of the edge each new
    vertex bisected."""
    origin = np.arange(len(f))
    parents = np.zeros((0, 2), dtype=np.int64)
    while True:
        edges, opposite = edge_table(f)
        uses = faces_per_edge(opposite, len(edges))
        length_m = np.linalg.norm(v[edges[:, 0]] - v[edges[:, 1]], axis=1)
        wanted = (length_m > target_edge_m * 4 / 3) & on_boundary[edges].any(axis=1)
        if not wanted.any():
            return v, f, origin, parents
        ok_face = ~(f[:, [0, 1, 2]] == f[:, [1, 2, 0]]).any(axis=1)
        corner = _longest_corner(length_m, opposite)
        longest = opposite[np.arange(len(f)), corner]
        needed = _chains(opposite, wanted, longest, ok_face)
        if len(rim) and (needed & _rows_in(edges, rim)).any():
            return None
        split_edge = needed & (np.bincount(longest[ok_face], minlength=len(uses)) == uses)
        if not split_edge.any():  # only where a face with a repeated corner blocks the chain
            return v, f, origin, parents
        new_index = np.full(len(edges), -1, dtype=np.int64)
        new_index[split_edge] = len(v) + np.arange(split_edge.sum())
        v = np.vstack([v, v[edges[split_edge]].mean(axis=1)])
        parents = np.vstack([parents, edges[split_edge]])
        on_boundary = np.concatenate([on_boundary, (uses == 1)[split_edge]])
        cut = np.nonzero(ok_face & split_edge[longest])[0]
        c = corner[cut]
        apex, a, b = f[cut, c], f[cut, (c + 1) % 3], f[cut, (c + 2) % 3]
        mid = new_index[longest[cut]]
        keep = np.ones(len(f), dtype=bool)
        keep[cut] = False
        f = np.vstack([f[keep], np.column_stack([apex, a, mid]),
                       np.column_stack([apex, mid, b])]).astype(np.int32)
        origin = np.concatenate([origin[keep], np.full(2 * len(cut), -1)])


def _longest_corner(length_m: FloatArray, opposite: NDArray[np.int64]) -> NDArray[np.int64]:
    """(F,) the corner opposite each face's longest edge, equal lengths going to the lower
    edge index: one order over all edges, so that the longest edge of a chain is the longest
    of every face it is in."""
    face_length = length_m[opposite]
    best = np.zeros(len(opposite), dtype=np.int64)
    rows = np.arange(len(opposite))
    for c in (1, 2):
        here, there = face_length[:, c], face_length[rows, best]
        better = (here > there) | ((here == there) & (opposite[:, c] < opposite[rows, best]))
        best[better] = c
    return best


def _chains(opposite: NDArray[np.int64], wanted: NDArray[np.bool_],
            longest: NDArray[np.int64], ok_face: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """(E,) the edges one round would bisect before the check that each is the longest of
    every face using it: the longest edges of the faces that hold a `wanted` edge, and,
    along the chain, the longest of each face beside an edge so chosen. After that check
    each face loses one edge at most, so the round's splits are independent; the longest
    chosen edge always passes it, so the rounds end (none: only where a face with a
    repeated corner blocks the chain)."""
    needed = np.zeros(len(wanted), dtype=bool)
    needed[longest[ok_face & wanted[opposite].any(axis=1)]] = True
    while True:
        grown = needed.copy()
        grown[longest[ok_face & needed[opposite].any(axis=1)]] = True
        if (grown == needed).all():
            return needed
        needed = grown
