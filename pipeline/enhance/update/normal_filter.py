"""Bilateral normal filtering and the vertex fit that follows it (Zheng et al. 2011, "Bilateral
normal filtering for mesh denoising"), the last step of the view-based update.

Each face normal is averaged with those of the faces that share a vertex with it, weighted by
their area, by the distance between the centroids and by how alike the normals are; then the
vertices move, along those normals only, so that the faces fit them. After the view update
the surface is smooth and what is left of the noise tilts faces against their neighbours:
the range weight lets a crease keep its two sides apart while that tilt is averaged away.
It is made for that input: noise of a fraction of an edge on edges short against the radius
of curvature. On raw noise of an edge or more the range weight shuts out every neighbour and
most of the noise stays, and on a coarse tessellation it bends a clean surface.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from pipeline.geometry.mesh import TriangleMesh, face_normals, mean_edge_length_m
from pipeline.geometry.repair import face_areas, faces_sharing_vertices

if TYPE_CHECKING:
    import torch

FloatArray = NDArray[np.float64]
Faces = NDArray[np.int32]


@dataclass(frozen=True)
class NormalFilterConfig:
    """How the face normals are filtered and the vertices fitted to them."""

    normal_iterations: int = 5
    """Rounds of bilateral averaging of the face normals (0: the filter is off)."""
    vertex_iterations: int = 10
    """Rounds of moving the vertices to fit the filtered normals."""
    range_sigma: float = 0.15
    """Width of the normal-likeness weight, as the distance between unit normals."""
    spatial_sigma_edges: float = 1.5
    """Width of the distance weight between face centroids, in mean edge lengths.

    The four settings are those of least C2M error after the update on the training meshes;
    nearby settings do about as well, so the filter is not tuned to a knife's edge."""

    def __post_init__(self) -> None:
        if self.normal_iterations < 0 or self.vertex_iterations < 0:
            raise ValueError("normal_filter: iterations must be >= 0")
        if not (self.range_sigma > 0 and self.spatial_sigma_edges > 0):
            raise ValueError("normal_filter: range_sigma and spatial_sigma_edges must be > 0")


def face_neighbours(faces: Faces, vertex_count: int
                    ) -> tuple[NDArray[np.int32], NDArray[np.int32]]:
    """The faces that share a vertex with each face, itself included, as CSR rows: (P,)
    neighbour indices and the (F + 1,) starts of each face's row in them."""
    pairs = faces_sharing_vertices(faces, vertex_count)
    return pairs.indices, pairs.indptr


def filtered_normals(vertices_m: FloatArray, faces: Faces, config: NormalFilterConfig,
                     device: str = "cpu") -> FloatArray:
    """(F, 3) the faces' unit normals after `config.normal_iterations` rounds of bilateral
    averaging over the faces that share a vertex (the spatial weight fixed by the input); the
    rounds run in torch on `device`.

    The products of each neighbour pair's normals (and, once, centroids) are formed only
    where the pair is, as a sampled product on the sparse pattern, then a round is one sparse
    product: cheaper than gathering both normals of every pair."""
    import torch

    from pipeline.enhance.device import accelerator, csr_tensor

    inputs = (_face_inputs_there if accelerator(device) else _face_inputs)(
        vertices_m, faces, device)
    starts, columns, centroids = inputs.row_starts, inputs.columns, inputs.centroids_m
    spatial_sigma_m = config.spatial_sigma_edges * inputs.mean_edge_m
    shape = (len(faces), len(faces))
    pattern = csr_tensor(starts, columns, centroids.new_zeros(len(columns)), shape)

    def pair_products(field: torch.Tensor) -> torch.Tensor:
        """(P,) each neighbour pair's product of `field`'s rows, in the pattern's order."""
        return torch.sparse.sampled_addmm(pattern, field, field.T.contiguous(), beta=0.0).values()

    # |c_f - c_g|² from products, about the centroids' mean so that they cancel less.
    squared = (centroids * centroids).sum(dim=1)
    gap_m2 = (squared.repeat_interleave(starts.diff()) + squared[columns]
              - 2.0 * pair_products(centroids)).clamp_min(0.0)
    # A face is its own neighbour: at no distance and alike, its weight is its area.
    near = inputs.areas_m2[columns] * torch.exp(-gap_m2 / (2 * spatial_sigma_m**2))
    n = inputs.normals
    for _ in range(config.normal_iterations):
        # |n_f - n_g|² = 2 - 2 n_f·n_g for unit normals.
        likeness = pair_products(n)
        averaging = csr_tensor(starts, columns,
                               near * torch.exp((likeness - 1.0) / config.range_sigma**2), shape)
        summed = averaging @ n
        n = summed / summed.norm(dim=1, keepdim=True).clamp_min(1e-300)
    return n.cpu().numpy()


@dataclass(frozen=True)
class FaceInputs:
    """What the filter reads of the faces, on its device."""

    normals: torch.Tensor
    """(F, 3) unit face normals."""
    areas_m2: torch.Tensor
    """(F,) face areas, square metres."""
    row_starts: torch.Tensor
    """(F + 1,) CSR row starts of the faces sharing a vertex with each face
    (`face_neighbours`)."""
    columns: torch.Tensor
    """(P,) those faces."""
    centroids_m: torch.Tensor
    """(F, 3) face centroids about their mean, metres."""
    mean_edge_m: float
    """The mean edge length, metres."""


def _face_inputs(vertices_m: FloatArray, faces: Faces, device: str) -> FaceInputs:
    """`FaceInputs` made in numpy and scipy, then moved to `device`."""
    from pipeline.enhance.device import csr_indices, on_device

    other, row_starts = face_neighbours(faces, len(vertices_m))
    starts, columns = csr_indices(row_starts, other, device)
    centroids_m = vertices_m[faces].mean(axis=1)
    return FaceInputs(on_device(face_normals(vertices_m, faces), device),
                      on_device(face_areas(vertices_m, faces), device), starts, columns,
                      on_device(centroids_m - centroids_m.mean(axis=0), device),
                      mean_edge_length_m(TriangleMesh(vertices_m=vertices_m, faces=faces)))


def _face_inputs_there(vertices_m: FloatArray, faces: Faces, device: str) -> FaceInputs:
    """`FaceInputs` made in torch on `device` (an accelerator), from the vertices and faces
    alone, so that nothing is built on the host."""
    import torch

    from pipeline.enhance import mesh_torch
    from pipeline.enhance.device import on_device

    v = on_device(vertices_m, device)
    f = on_device(faces.astype(np.int64), device)
    tri = v[f]
    cross = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    starts, columns = mesh_torch.faces_sharing_vertices(f, len(vertices_m))
    centroids_m = tri.mean(dim=1)
    return FaceInputs(mesh_torch.face_normals(v, f), 0.5 * torch.linalg.vector_norm(cross, dim=1),
                      starts, columns, centroids_m - centroids_m.mean(dim=0),
                      mesh_torch.mean_edge_length_m(v, f))


def fit_to_normals(vertices_m: FloatArray, faces: Faces, normals: FloatArray,
                   iterations: int, device: str = "cpu") -> FloatArray:
    """(V, 3) vertices moved so that the faces lie across `normals` (F, 3): each round moves
    a vertex by the mean, over its faces, of its offset to the face's centroid along the face's
    normal (Sun et al. 2007), so vertices move along the normals only. In torch on `device`.

    That mean is (Σ_f n_f (n_f · c_f) - (Σ_f n_f n_fᵀ) x) / k over a vertex's k faces; the
    normals are fixed, so each vertex's 3 × 3 sum is formed once and a round costs one face
    sum."""
    import torch

    from pipeline.enhance.device import accelerator, on_device

    at_vertices, centroids, face_count = (_face_sums_there if accelerator(device)
                                          else _face_sums)(faces, len(vertices_m), device)
    n = on_device(normals, device)
    projectors = at_vertices(torch.einsum("fi,fj->fij", n, n).reshape(-1, 9)).reshape(-1, 3, 3)
    out = on_device(vertices_m, device)
    for _ in range(iterations):
        plane_offset_m = (n * centroids(out)).sum(dim=1, keepdim=True)
        toward_planes = at_vertices(n * plane_offset_m) - torch.einsum(
            "vij,vj->vi", projectors, out)
        out = out + toward_planes / face_count
    return out.cpu().numpy()


FaceSums = tuple[Callable[["torch.Tensor"], "torch.Tensor"],
                 Callable[["torch.Tensor"], "torch.Tensor"], "torch.Tensor"]
"""On the fit's device: (F, C) -> (V, C) each vertex's sum over its faces, (V, 3) -> (F, 3)
each face's centroid, and (V, 1) each vertex's count of faces (at least 1)."""


def _face_sums(faces: Faces, vertex_count: int, device: str) -> FaceSums:
    """`FaceSums` as sparse products with matrices made in scipy."""
    from pipeline.enhance.device import csr_on_device, on_device

    corners = faces.ravel()
    summing = sp.csr_matrix(
        (np.ones(len(corners)), (corners, np.repeat(np.arange(len(faces)), 3))),
        shape=(vertex_count, len(faces)))
    over_faces = csr_on_device(summing, device)
    centroid_of = csr_on_device((summing.T / 3.0).tocsr(), device)
    face_count = on_device(np.maximum(np.asarray(summing.sum(axis=1)), 1), device)
    return (lambda x: over_faces @ x), (lambda v: centroid_of @ v), face_count


def _face_sums_there(faces: Faces, vertex_count: int, device: str) -> FaceSums:
    """`FaceSums` as gathers and scatters on `device` (an accelerator), with nothing made on
    the host."""
    import torch

    from pipeline.enhance.device import on_device

    f = on_device(faces.astype(np.int64), device)

    def at_vertices(x: torch.Tensor) -> torch.Tensor:
        out = x.new_zeros((vertex_count, x.shape[1]))
        for corner in range(3):
            out.index_add_(0, f[:, corner], x)
        return out

    face_count = torch.bincount(f.reshape(-1), minlength=vertex_count).clamp_min(1)
    return at_vertices, (lambda v: v[f].mean(dim=1)), face_count[:, None].double()


def normal_filter(mesh: TriangleMesh, config: NormalFilterConfig, device: str = "cpu"
                  ) -> TriangleMesh:
    """The mesh with its face normals bilaterally filtered and its vertices fitted to them,
    in torch on `device`; the mesh itself where `config.normal_iterations` is 0."""
    if config.normal_iterations == 0:
        return mesh
    normals = filtered_normals(mesh.vertices_m, mesh.faces, config, device)
    return mesh.with_vertices(fit_to_normals(mesh.vertices_m, mesh.faces, normals,
                                             config.vertex_iterations, device))
