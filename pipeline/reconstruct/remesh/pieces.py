"""The remesh kernel's work split into spatial pieces that remesh side by side.

The kernel (gpytoolbox's ``remesh_botsch``) is single-threaded, and it holds every boundary
vertex of what it is given: neither moved, nor removed, nor joined by a new edge split. So a
mesh whose faces are in a spatial order (`geometry.order`) can be cut into runs of faces, each
run remeshed in its own process with the cut held like a boundary, and the results joined
again at the held vertices, which every piece keeps by the input's index. No seam is matched
by position, so none can open.

What it costs: the cut's vertices keep their place and the cut's edges stay, so near it the
kernel only relaxes the free side. That is harmless where the kernel runs at the mesh's own
edge length (the enhancement's light remesh: the pieces' accuracy matches one whole run's),
but a remesh to a much longer target would keep a seam of short edges, so only the light
remesh asks for pieces.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from pipeline.geometry.repair import edge_table, faces_per_edge, used_vertices

FloatArray = NDArray[np.float64]
Faces = NDArray[np.int32]


@dataclass(frozen=True)
class Piece:
    """A run of the input's faces, over its own vertices."""

    vertex_ids: NDArray[np.int64]
    """(Vp,) the input's index of each of the piece's vertices, ascending."""
    faces: Faces
    """(Fp, 3) the faces, indexing `vertex_ids`."""


def held_vertices(faces: Faces) -> NDArray[np.int64]:
    """(H,) ascending, the vertices on the boundary of `faces` (on an edge one face uses):
    those the kernel holds, and returns first in this order (its `held`)."""
    edges, opposite = edge_table(faces)
    return np.unique(edges[faces_per_edge(opposite, len(edges)) == 1])


def spatial_pieces(faces: Faces, count: int) -> list[Piece]:
    """`faces` cut into `count` runs of about equal length, in their order: contiguous
    pieces where the faces are in a spatial order."""
    pieces = []
    vertex_count = int(faces.max(initial=-1)) + 1
    for run in np.array_split(faces, count):
        vertex_ids, local_faces = used_vertices(run, vertex_count)
        pieces.append(Piece(vertex_ids, local_faces))
    return pieces


def stitched(vertices_m: FloatArray, pieces: list[Piece],
             results: Sequence[tuple[FloatArray, Faces, NDArray[np.int64]]]
             ) -> tuple[FloatArray, Faces, NDArray[np.int64]]:
    """The pieces' kernel results (vertices, faces, and the piece's vertices it held, which
    come first: the kernel's `held`, the piece's `held_vertices`) joined into one mesh: each
    held vertex becomes the input vertex it came from, the rest are appended; input vertices
    no face uses any more are dropped. Returns the vertices, the faces and (V',) each
    vertex's row in the input's vertices followed by each piece's new ones in turn. A
    ValueError where a piece moved a vertex it should have held."""
    out_vertices = [vertices_m]
    out_faces = []
    next_id = len(vertices_m)
    for k, (piece, (piece_vertices_m, piece_faces, held)) in enumerate(zip(pieces, results,
                                                                           strict=True)):
        held_ids = piece.vertex_ids[held]
        if not np.array_equal(piece_vertices_m[: len(held_ids)], vertices_m[held_ids]):
            raise ValueError(f"remesh piece {k}: the kernel moved a vertex of its cut")
        new_count = len(piece_vertices_m) - len(held_ids)
        to_output = np.concatenate([held_ids, next_id + np.arange(new_count)])
        out_vertices.append(piece_vertices_m[len(held_ids):])
        out_faces.append(to_output[piece_faces])
        next_id += new_count
    used, faces = used_vertices(np.concatenate(out_faces), next_id)
    return np.concatenate(out_vertices)[used], faces, used


def stitched_sources(vertex_count: int, pieces: list[Piece],
                     sources: Sequence[tuple[NDArray[np.int64], FloatArray, int]],
                     rows: NDArray[np.int64]) -> tuple[NDArray[np.int64], FloatArray]:
    """The joined mesh's vertices as points of the input's faces: (V', 3) input vertex ids and
    (V', 3) weights, from each piece's kernel `sources` (ids into the piece's vertices,
    weights, and how many vertices it held) and `stitched`'s `rows`, ascending (the input's
    vertices first), as `stitched` gives them. An input vertex is itself, weight 1."""
    ids, weights = [], []
    for piece, (piece_ids, piece_weights, held_count) in zip(pieces, sources, strict=True):
        ids.append(piece.vertex_ids[piece_ids[held_count:]])
        weights.append(piece_weights[held_count:])
    # `rows` ascends, so the input's vertices come first.
    inputs = int(np.searchsorted(rows, vertex_count))
    out_ids = np.empty((len(rows), 3), dtype=np.int64)
    out_weights = np.zeros((len(rows), 3))
    out_ids[:inputs] = rows[:inputs, None]
    out_weights[:inputs, 0] = 1.0
    new_rows = rows[inputs:] - vertex_count
    out_ids[inputs:] = np.concatenate(ids)[new_rows]
    out_weights[inputs:] = np.concatenate(weights)[new_rows]
    return out_ids, out_weights
