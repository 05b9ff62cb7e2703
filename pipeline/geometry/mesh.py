"""The triangle mesh that stages pass around."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class TriangleMesh:
    """An indexed triangle mesh in metres (world frame unless said otherwise)."""

    vertices_m: NDArray[np.float64]
    """(V, 3) vertex positions, metres."""
    faces: NDArray[np.int32]
    """(F, 3) vertex indices, counter-clockwise seen from outside."""
    vertex_colors: NDArray[np.uint8] | None = None
    """(V, 3) sRGB colours, or None."""
    vertex_normals: NDArray[np.float32] | None = None
    """(V, 3) unit normals, or None."""

    @property
    def vertex_count(self) -> int:
        return int(self.vertices_m.shape[0])

    @property
    def face_count(self) -> int:
        return int(self.faces.shape[0])

    def with_vertices(self, vertices_m: NDArray[np.float64]) -> TriangleMesh:
        """The same connectivity and colours at new positions (normals dropped: they changed)."""
        return replace(self, vertices_m=vertices_m, vertex_normals=None)


FACE_BLOCK_FACES = 8192
"""Faces the per-face geometry (`face_cross_m2`, `repair.face_areas`,
`repair.triangle_angles_deg`) takes at a time: its temporaries then stay in the cache rather
than each going out to memory, with the same bits."""


def face_blocks(face_count: int) -> list[slice]:
    """`face_count` faces cut into runs of `FACE_BLOCK_FACES`."""
    return [slice(start, start + FACE_BLOCK_FACES)
            for start in range(0, face_count, FACE_BLOCK_FACES)]


def coordinate_columns_m(vertices_m: NDArray[np.float64]) -> NDArray[np.float64]:
    """(3, V) the x, y and z of (V, 3) `vertices_m`, each contiguous: gathers from a column
    are a third quicker than gathers of rows."""
    return np.ascontiguousarray(np.asarray(vertices_m, np.float64).T)


def face_cross_columns_m2(columns: NDArray[np.float64], faces: NDArray[np.integer]
                          ) -> tuple[NDArray[np.float64], ...]:
    """The x, y and z, each (F,), of each of `faces`' (b - a) x (c - a), from the vertices'
    `coordinate_columns_m`."""
    index = faces.T.astype(np.intp)
    x, y, z = columns
    x0, y0, z0 = x.take(index[0]), y.take(index[0]), z.take(index[0])
    ax, ay, az = x.take(index[1]) - x0, y.take(index[1]) - y0, z.take(index[1]) - z0
    bx, by, bz = x.take(index[2]) - x0, y.take(index[2]) - y0, z.take(index[2]) - z0
    return ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx


def face_cross_m2(vertices_m: NDArray[np.float64], faces: NDArray[np.int32]
                  ) -> NDArray[np.float64]:
    """(F, 3) each face's (b - a) x (c - a), twice its area along its normal, square metres:
    written out on the coordinates' columns, three to four times as fast as ``np.cross`` on
    gathered (F, 3, 3) corners, with the same bits; by `face_blocks`."""
    columns = coordinate_columns_m(vertices_m)
    cross = np.empty((len(faces), 3))
    for block in face_blocks(len(faces)):
        for k, component in enumerate(face_cross_columns_m2(columns, faces[block])):
            cross[block, k] = component
    return cross


def face_normals(vertices_m: NDArray[np.float64], faces: NDArray[np.int32]) -> NDArray[np.float64]:
    """(F, 3) unit face normals (zero for degenerate faces)."""
    normals = face_cross_m2(vertices_m, faces)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)


def vertex_normals(
    vertices_m: NDArray[np.float64], faces: NDArray[np.int32]
) -> NDArray[np.float32]:
    """(V, 3) area-weighted unit vertex normals."""
    weighted = face_cross_m2(vertices_m, faces)
    # Corner by corner in face order, the order np.add.at would sum in, at a tenth of its time.
    corners = faces.T.ravel()
    normals = np.stack([np.bincount(corners, np.tile(weighted[:, k], 3), len(vertices_m))
                        for k in range(3)], axis=1)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    unit = np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)
    return unit.astype(np.float32)


def mean_edge_length_m(mesh: TriangleMesh) -> float:
    """Mean length of the faces' edges (an interior edge counted once per face), metres."""
    columns = coordinate_columns_m(mesh.vertices_m)
    # Each corner gathered once, coordinate by coordinate: the same lengths in the same
    # order as np.linalg.norm of both ends' gathered rows, so the same mean bit for bit, at
    # a third of the time (numpy reduces an (N, 3) array along its rows slowly).
    corners = [[axis[mesh.faces[:, c]] for axis in columns] for c in range(3)]
    lengths_m = []
    for a, b in zip(corners, corners[1:] + corners[:1], strict=True):
        dx, dy, dz = (p - q for p, q in zip(a, b, strict=True))
        lengths_m.append(np.sqrt(dx * dx + dy * dy + dz * dz))
    return float(np.concatenate(lengths_m).mean())
