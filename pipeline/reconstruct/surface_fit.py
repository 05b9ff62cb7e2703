"""Surface fit: the remeshed surface moved back onto the refined points it came from.

Screened Poisson at 16 mm cells smooths away what is smaller than a few cells (a crease, a
lip, an ear's rim) and the remesh projects onto that smoothed surface. Each vertex is moved
along its normal to the weighted mean offset of its nearest refined points: a local plane
fit at the vertex, as dense as the cloud is, which puts the detail back at the cost of a
neighbour query (docs/decisions/surface-fit.md). Where the surface bends between two
vertices by more than the remesh's edges can follow, the cloud's plane at the edge's
midpoint lies off the edge, and the edge is split there (docs/decisions/fit-edge-splits.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from pipeline.geometry.mesh import TriangleMesh, vertex_normals
from pipeline.geometry.repair import edge_table
from pipeline.geometry.subdivide import split_edges

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
    split_tolerance_m: float = 0.00025
    """An edge is split where the cloud's plane at its midpoint lies farther than this from
    it, metres. A 12 mm edge on a curve of radius r lies 18 mm**2 / r from it at its middle:
    0.25 mm is a radius of 7 cm, so a head or a torso keeps its edges and an ear's rim, a
    nose, a finger or a fold gets vertices 6 mm apart."""
    split_significance: float = 1.0
    """... and farther than this many standard errors of that plane's fit: where the cloud
    is too noisy to tell (far, binned, quantised depth), edges stay whole."""

    def __post_init__(self) -> None:
        if self.neighbours < 1 or self.min_points < 1:
            raise ValueError("surface_fit: neighbours and min_points must be >= 1")
        if not (self.search_radius_m > 0 and self.max_shift_m > 0):
            raise ValueError("surface_fit: search_radius_m and max_shift_m must be > 0")
        if not -1 <= self.min_normal_cosine <= 1:
            raise ValueError("surface_fit: min_normal_cosine must lie in [-1, 1]")
        if not (self.split_tolerance_m > 0 and self.split_significance >= 0):
            raise ValueError("surface_fit: split_tolerance_m must be > 0 and "
                             "split_significance >= 0")
        if not (self.threads == -1 or self.threads >= 1):
            raise ValueError("surface_fit: threads must be >= 1 (-1: every core)")


def normal_shifts_m(vertices_m: FloatArray, normals: FloatArray, points_world: FloatArray,
                    point_normals: NDArray[np.floating], tree: cKDTree,
                    config: SurfaceFitConfig) -> tuple[FloatArray, FloatArray]:
    """(N,) signed distance along each of (N, 3) unit `normals` from (N, 3) `vertices_m` to
    the local plane of the cloud, metres, and (N,) its standard error (both 0 where fewer
    than `min_points` points count).

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
    offset = np.take(points_world, near, axis=0) - vertices_m[:, None, :]
    along = np.einsum("vkc,vc->vk", offset, normals)
    # |offset| is the query's distance, so the part across the normal needs no 3-vectors.
    across = np.sqrt(np.maximum(np.where(found, dist, 0.0) ** 2 - along**2, 0.0))
    facing = np.einsum("vkc,vc->vk", np.take(point_normals, near, axis=0), normals)
    usable = found & (np.abs(along) <= config.max_shift_m) & (
        facing >= config.min_normal_cosine)
    # Every found point lies within `reach`, so the kernel is never negative where it counts.
    reach = across.max(axis=1, keepdims=True)
    weight = np.where(usable, (1.0 - (across / np.maximum(reach, 1e-12)) ** 2) ** 2, 0.0)
    total = np.maximum(weight.sum(axis=1), 1e-300)
    shift = (weight * along).sum(axis=1) / total
    variance = (weight * (along - shift[:, None]) ** 2).sum(axis=1) / total
    # Kish's effective number of points: the weights make some count less than one.
    effective = total**2 / np.maximum((weight**2).sum(axis=1), 1e-300)
    error = np.sqrt(variance / np.maximum(effective - 1.0, 1.0))
    fitted = np.count_nonzero(weight, axis=1) >= config.min_points
    return np.where(fitted, shift, 0.0), np.where(fitted, error, 0.0)


def fit_to_cloud(mesh: TriangleMesh, points_world: FloatArray,
                 normals_world: NDArray[np.floating], config: SurfaceFitConfig
                 ) -> tuple[TriangleMesh, int]:
    """The mesh with each vertex moved along its normal onto the refined cloud's local plane,
    then each edge whose midpoint that plane puts off the edge (`split_tolerance_m`,
    `split_significance`) split at the plane; and how many edges were split.

    ``points_world`` (N, 3) metres and ``normals_world`` (N, 3) unit normals: the refined
    points.
    """
    if len(points_world) == 0 or mesh.vertex_count == 0:
        return mesh, 0
    tree = cKDTree(points_world)
    normals = vertex_normals(mesh.vertices_m, mesh.faces).astype(np.float64)
    shift_m, _ = _shifts_m(mesh.vertices_m, normals, points_world, normals_world, tree, config)
    vertices_m = mesh.vertices_m + shift_m[:, None] * normals
    edges, _ = edge_table(mesh.faces)
    edge_normals = vertex_normals(vertices_m, mesh.faces).astype(np.float64)[edges].sum(axis=1)
    edge_normals /= np.maximum(np.linalg.norm(edge_normals, axis=1, keepdims=True), 1e-12)
    midpoints_m = vertices_m[edges].mean(axis=1)
    shift_m, error_m = _shifts_m(midpoints_m, edge_normals, points_world, normals_world, tree,
                                 config)
    split = np.abs(shift_m) > np.maximum(config.split_tolerance_m,
                                         config.split_significance * error_m)
    vertices_m, faces = split_edges(vertices_m, mesh.faces, split,
                                    midpoints_m + shift_m[:, None] * edge_normals)
    return TriangleMesh(vertices_m=vertices_m, faces=faces), int(np.count_nonzero(split))


def _shifts_m(points_m: FloatArray, normals: FloatArray, points_world: FloatArray,
              normals_world: NDArray[np.floating], tree: cKDTree, config: SurfaceFitConfig
              ) -> tuple[FloatArray, FloatArray]:
    """`normal_shifts_m` in batches of `CHUNK_VERTICES`."""
    shift_m, error_m = np.zeros(len(points_m)), np.zeros(len(points_m))
    for start in range(0, len(points_m), CHUNK_VERTICES):
        part = slice(start, start + CHUNK_VERTICES)
        shift_m[part], error_m[part] = normal_shifts_m(points_m[part], normals[part],
                                                       points_world, normals_world, tree,
                                                       config)
    return shift_m, error_m
