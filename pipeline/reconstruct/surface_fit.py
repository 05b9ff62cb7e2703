"""Surface fit: the remeshed surface moved back onto the refined points it came from.

Screened Poisson at 16 mm cells smooths away what is smaller than a few cells (a crease, a
lip, an ear's rim) and the remesh projects onto that smoothed surface. Each vertex is moved
along its normal to the weighted mean offset of its nearest refined points: a local plane
fit at the vertex, as dense as the cloud is, which puts the detail back at the cost of a
neighbour query (docs/decisions/surface-fit.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from pipeline.geometry.mesh import TriangleMesh, vertex_normals

FloatArray = NDArray[np.float64]
CHUNK_VERTICES = 65_536
"""Vertices fitted per batch (bounds the (batch, neighbours, 3) offsets' memory)."""


@dataclass(frozen=True)
class SurfaceFitConfig:
    """How the remeshed vertices are fitted to the refined cloud."""

    neighbours: int = 32
    """Nearest refined points each vertex is fitted to: a disk as wide as the cloud is
    sparse (about 1 cm across at the Kinect's full depth mode and 1.8 m). More smooths
    creases again; fewer lets the sensor's noise through."""
    search_radius_m: float = 0.03
    """Points farther than this from the vertex are never used, metres."""
    max_shift_m: float = 0.012
    """Points farther than this from the vertex's tangent plane are ignored (another sheet
    of the surface, an outlier), so no vertex moves farther, metres."""
    min_normal_cosine: float = 0.5
    """Points whose normal makes a larger angle with the vertex's are ignored: the other
    side of a thin part faces away."""
    min_points: int = 3
    """Vertices with fewer usable points stay where they are (surface nobody saw)."""
    threads: int = 2
    """Threads of the neighbour query (-1: every core)."""

    def __post_init__(self) -> None:
        if self.neighbours < 1 or self.min_points < 1:
            raise ValueError("surface_fit: neighbours and min_points must be >= 1")
        if not (self.search_radius_m > 0 and self.max_shift_m > 0):
            raise ValueError("surface_fit: search_radius_m and max_shift_m must be > 0")
        if not -1 <= self.min_normal_cosine <= 1:
            raise ValueError("surface_fit: min_normal_cosine must lie in [-1, 1]")
        if not (self.threads == -1 or self.threads >= 1):
            raise ValueError("surface_fit: threads must be >= 1 (-1: every core)")


def normal_shifts_m(vertices_m: FloatArray, normals: FloatArray, points_world: FloatArray,
                    point_normals: NDArray[np.floating], tree: cKDTree,
                    config: SurfaceFitConfig) -> FloatArray:
    """(V,) signed distance along each unit normal to the local plane of the cloud, metres.

    Each vertex's nearest points are weighted by a Wendland kernel of their distance across
    the normal, scaled to the farthest of them, so the fit is centred on the vertex whatever
    the cloud's density.
    """
    k = min(config.neighbours, tree.n)
    dist, near = tree.query(vertices_m, k=k, distance_upper_bound=config.search_radius_m,
                            workers=config.threads)
    dist, near = dist.reshape(len(vertices_m), k), near.reshape(len(vertices_m), k)
    found = np.isfinite(dist)
    near = np.where(found, near, 0)
    offset = points_world[near] - vertices_m[:, None, :]
    along = np.einsum("vkc,vc->vk", offset, normals)
    across = np.linalg.norm(offset - along[..., None] * normals[:, None, :], axis=2)
    facing = np.einsum("vkc,vc->vk", point_normals[near].astype(np.float64), normals)
    usable = found & (np.abs(along) <= config.max_shift_m) & (
        facing >= config.min_normal_cosine)
    # Every found point lies within `reach`, so the kernel is never negative where it counts.
    reach = np.where(found, across, 0.0).max(axis=1, keepdims=True)
    weight = np.where(usable, (1.0 - (across / np.maximum(reach, 1e-12)) ** 2) ** 2, 0.0)
    shift = (weight * along).sum(axis=1) / np.maximum(weight.sum(axis=1), 1e-300)
    return np.where(np.count_nonzero(weight, axis=1) >= config.min_points, shift, 0.0)


def fit_to_cloud(mesh: TriangleMesh, points_world: FloatArray,
                 normals_world: NDArray[np.floating], config: SurfaceFitConfig
                 ) -> TriangleMesh:
    """The mesh with each vertex moved along its normal onto the refined cloud's local plane.

    ``points_world`` (N, 3) metres and ``normals_world`` (N, 3) unit normals: the refined
    points. The faces are kept.
    """
    if len(points_world) == 0 or mesh.vertex_count == 0:
        return mesh
    normals = vertex_normals(mesh.vertices_m, mesh.faces).astype(np.float64)
    tree = cKDTree(points_world)
    vertices = mesh.vertices_m.copy()
    for start in range(0, mesh.vertex_count, CHUNK_VERTICES):
        part = slice(start, start + CHUNK_VERTICES)
        shift = normal_shifts_m(mesh.vertices_m[part], normals[part], points_world,
                                normals_world, tree, config)
        vertices[part] += shift[:, None] * normals[part]
    return TriangleMesh(vertices_m=vertices, faces=mesh.faces)
