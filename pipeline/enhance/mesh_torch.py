"""Mesh quantities in torch, on the enhancement's device: what `pipeline.geometry.mesh`,
`pipeline.geometry.repair`, `pipeline.geometry.boundary` and
`pipeline.geometry.smoothing.mean_operator` give in numpy and scipy, for the torch
implementations of the stages, so that on a GPU the mesh need not go back to the host."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from pipeline.enhance.device import csr_tensor


def vertex_normals(vertices_m: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """(V, 3) float32 area-weighted unit vertex normals of (V, 3) vertices and (F, 3) int64
    faces (zero where the faces about a vertex cancel): float32, as
    `pipeline.geometry.mesh`'s, so both implementations agree to its rounding."""
    tri = vertices_m[faces]
    weighted = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals = torch.zeros_like(vertices_m)
    for corner in range(3):
        normals.index_add_(0, faces[:, corner], weighted)
    length = torch.linalg.vector_norm(normals, dim=1, keepdim=True)
    return torch.where(length > 0, normals / length.clamp_min(1e-300), 0.0).float()


def face_normals(vertices_m: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """(F, 3) unit face normals (zero for degenerate faces), as `pipeline.geometry.mesh`'s."""
    tri = vertices_m[faces]
    normals = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = torch.linalg.vector_norm(normals, dim=1, keepdim=True)
    return torch.where(length > 0, normals / length.clamp_min(1e-300), 0.0)


def triangle_angles_deg(vertices_m: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """(F, 3) interior angle at each corner of (F, 3) int64 `faces`, degrees (0 for
    degenerate), in `vertices_m`'s dtype: `pipeline.geometry.repair.triangle_angles_deg`'s
    steps in its order, so both agree to the rounding of their arccos."""
    corner = vertices_m[faces]
    side = corner.roll(-1, dims=1) - corner  # side c runs from corner c to corner c + 1
    x, y, z = side.unbind(dim=2)
    length = torch.sqrt(x * x + y * y + z * z)
    before, length_before = side.roll(1, dims=1), length.roll(1, dims=1)
    u, v, w = before.unbind(dim=2)
    dot = x * u + y * v + z * w
    denom = length * length_before
    positive = denom > 0
    cos = torch.where(positive, -dot / torch.where(positive, denom, 1.0), 1.0)
    return torch.rad2deg(torch.arccos(cos.clamp(-1.0, 1.0)))


def mean_edge_length_m(vertices_m: torch.Tensor, faces: torch.Tensor) -> float:
    """Mean length of the faces' edges (an interior edge counted once per face), metres."""
    corners = vertices_m[faces]
    return float(torch.linalg.vector_norm(corners - corners.roll(-1, dims=1), dim=2).mean())


@dataclass(frozen=True)
class NeighbourPattern:
    """Each vertex's neighbours and itself, in row-major order: the entries of every
    operator `mean_operator` makes, built once from the faces (the sort is most of it)."""

    rows: torch.Tensor
    """(E,) int64 row of each entry, ascending."""
    columns: torch.Tensor
    """(E,) int64 column of each entry, ascending within a row."""
    neighbour_count: torch.Tensor
    """(V,) int64 neighbours of each vertex (0: isolated)."""

    @property
    def vertex_count(self) -> int:
        return len(self.neighbour_count)


def neighbour_pattern(faces: torch.Tensor, vertex_count: int) -> NeighbourPattern:
    """The `NeighbourPattern` of (F, 3) int64 faces on their device."""
    ends = [faces.roll(-shift, dims=1).reshape(-1) for shift in (0, 1)]
    diagonal = torch.arange(vertex_count, device=faces.device) * (vertex_count + 1)
    keys = torch.cat([ends[0] * vertex_count + ends[1], ends[1] * vertex_count + ends[0],
                      diagonal])
    keys = torch.unique(keys)  # sorted: row-major, each edge once each way
    rows, columns = keys // vertex_count, keys % vertex_count
    count = torch.bincount(rows, minlength=vertex_count) - 1
    return NeighbourPattern(rows, columns, count)


def mean_operator(pattern: NeighbourPattern, self_weight: float = 0.0,
                  dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """(V, V) sparse CSR (1 - w) M + w I, M the row-normalised adjacency (row i averages i's
    neighbours; an isolated vertex: itself), w `self_weight`; columns sorted; values computed
    in float64, then `dtype`. w = 0 is `pipeline.geometry.smoothing.mean_operator` (no entry
    on the diagonal but an isolated vertex's), w = 0.5 one Laplacian step
    (`pipeline.geometry.smoothing.twice_field`)."""
    rows, columns, count = pattern.rows, pattern.columns, pattern.neighbour_count
    lonely = (count == 0).to(torch.float64)
    on_diagonal = rows == columns
    if self_weight == 0.0:
        kept = ~on_diagonal | (count[rows] == 0)
        rows, columns, on_diagonal = rows[kept], columns[kept], on_diagonal[kept]
    neighbour_weight = (1.0 - self_weight) / count.clamp_min(1).to(torch.float64)
    diagonal = self_weight + (1.0 - self_weight) * lonely
    values = torch.where(on_diagonal, diagonal[rows], neighbour_weight[rows])
    return csr_tensor(*csr_rows(rows, columns, pattern.vertex_count), values.to(dtype),
                      (pattern.vertex_count, pattern.vertex_count))


def faces_sharing_vertices(faces: torch.Tensor, vertex_count: int
                           ) -> tuple[torch.Tensor, torch.Tensor]:
    """The faces that share a vertex with each of (F, 3) int64 faces, itself included, as
    CSR rows on their device: (F + 1,) row starts and the (P,) columns, ascending in a row
    (`pipeline.geometry.repair.faces_sharing_vertices`' pattern)."""
    face_count = len(faces)
    corner_vertex = faces.reshape(-1)
    by_vertex = torch.argsort(corner_vertex, stable=True)
    face_of = torch.arange(face_count, device=faces.device).repeat_interleave(3)[by_vertex]
    per_vertex = torch.bincount(corner_vertex, minlength=vertex_count)
    first = torch.cumsum(per_vertex, 0) - per_vertex
    # Each corner pairs with every corner at its vertex.
    shares = per_vertex[corner_vertex[by_vertex]]
    pair_first = torch.cumsum(shares, 0) - shares
    within = torch.arange(int(shares.sum()), device=faces.device) - pair_first.repeat_interleave(
        shares)
    partner = first[corner_vertex[by_vertex]].repeat_interleave(shares) + within
    keys = torch.unique(face_of.repeat_interleave(shares) * face_count + face_of[partner])
    return csr_rows(keys // face_count, keys % face_count, face_count)


def boundary_half_edges(faces: torch.Tensor, vertex_count: int) -> torch.Tensor:
    """(B, 2) int64 the directed edges of (F, 3) int64 faces, in their face's winding, that only
    one face uses, in face then corner order
    (`pipeline.geometry.boundary.boundary_half_edges`' order)."""
    # Corner c's opposite edge runs from corner c + 1 to corner c + 2.
    half = torch.stack([faces.roll(-1, dims=1), faces.roll(-2, dims=1)], dim=2).reshape(-1, 2)
    low, high = torch.minimum(half[:, 0], half[:, 1]), torch.maximum(half[:, 0], half[:, 1])
    # A key unlike both its sorted neighbours is an edge one face uses: cheaper than
    # torch.unique's inverse and counts.
    keys, order = torch.sort(low * vertex_count + high)
    alone = torch.ones(len(keys), dtype=torch.bool, device=keys.device)
    alone[1:] &= keys[1:] != keys[:-1]
    alone[:-1] &= keys[:-1] != keys[1:]
    return half[torch.sort(order[alone]).values]


def csr_rows(rows: torch.Tensor, columns: torch.Tensor, row_count: int
             ) -> tuple[torch.Tensor, torch.Tensor]:
    """CSR row starts (row_count + 1,) and columns of entries given by (E,) ascending `rows`
    and their `columns`, int32 where they fit: torch's CPU kernel for int64 ones is much
    slower, and on any device sparse products read half the index bytes."""
    row_starts = torch.zeros(row_count + 1, dtype=torch.int64, device=rows.device)
    row_starts[1:] = torch.cumsum(torch.bincount(rows, minlength=row_count), 0)
    index = torch.int32 if len(rows) < 2**31 - 1 else torch.int64
    return row_starts.to(index), columns.to(index)
