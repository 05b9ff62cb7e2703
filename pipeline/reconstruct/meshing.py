"""Meshing: Poisson-disk samples of the refined cloud, then a surface.

The surface is open3d's screened Poisson reconstruction of the oriented samples, trimmed
where it strays from them. A Delaunay-based surface (restricted Delaunay / cocone) would leave
holes wherever the samples are sparse (grazing views, seams between cameras) and need a
manifold repair before remeshing; screened Poisson fills those holes with a smooth,
watertight, manifold surface, and trimming what lies far from every sample keeps it honest
where no camera saw anything.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from pipeline.geometry.mesh import TriangleMesh
from pipeline.geometry.repair import compact, drop_small_components
from pipeline.reconstruct.voxel_refine import pack_keys

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class MeshingConfig:
    """How the refined cloud becomes a triangle mesh."""

    sample_radius_m: float = 0.006
    """Poisson-disk radius: no two samples are nearer than this, metres."""
    average_samples: bool = True
    """Move each sample along its normal to the mean of the refined points in a disk of one
    radius around it (less noise)."""
    average_neighbours: int = 16
    """At most this many nearest points (within two radii) are averaged per sample."""
    poisson_depth: int = 0
    """Deepest octree level of the screened Poisson solve (cell = cube side / 2**depth);
    0: the smallest depth whose cells are at most ``poisson_cell_m``."""
    poisson_cell_m: float = 0.016
    """Largest finest-cell size when the depth is automatic, metres. 16 mm (depth 7 for a
    1.8 m subject) puts the iso-surface well within a millimetre of smooth samples; halving
    it makes the solve about three times slower."""
    poisson_max_depth: int = 10
    """Upper bound of the automatic depth (time and memory grow about 3-4x per level). 10
    keeps the cells within ``poisson_cell_m`` up to a scene of about 15 m (a room: 8 mm
    cells for a room 8 m across, where 17 mm cells smooth away what a camera at 2-3 m
    sees); a subject in a rig never reaches it."""
    poisson_linear_fit: bool = False
    """Place iso-vertices by linear interpolation of the implicit function."""
    poisson_scale: float = 1.1
    """Ratio of the Poisson cube to the samples' bounding box."""
    trim_distance_m: float = 0.012
    """Vertices farther than this from every sample are removed (surface nobody saw)."""
    trim_spacing_factor: float = 2.0
    """...or farther than this many median sample spacings, when that is more: sparse
    clouds (small or distant depth images) keep a closed surface between their samples."""
    trim_density_quantile: float = 0.0
    """Vertices whose Poisson density is below this quantile are removed too (0: off; a
    fixed share cuts sparsely but truly seen regions, e.g. surfaces seen obliquely)."""
    min_component_share: float = 0.0
    """Connected pieces with fewer triangles than this share of the largest are dropped
    (0: off; a scene seen from afar, a room, breaks into many small true pieces)."""
    min_component_samples: int = 3
    """Connected pieces that fewer than this many samples lie on (within the trim
    distance) are dropped: stray bits that almost nothing was seen on."""
    threads: int = 2
    """Threads of the neighbour queries (their results do not depend on it; -1: every
    core)."""
    poisson_threads: int = 1
    """Threads of the Poisson solve. More than one gives another surface from run to run,
    and not only in the last bits (even the triangle count changes); one gives the same mesh
    every time (docs/decisions/poisson-one-thread.md)."""
    seed: int = 0
    """Seed of the sampling order (results are deterministic for a seed)."""

    def __post_init__(self) -> None:
        if not (self.sample_radius_m > 0 and self.trim_distance_m > 0):
            raise ValueError("meshing: sample_radius_m and trim_distance_m must be > 0")
        if not (self.poisson_depth == 0 or 4 <= self.poisson_depth <= 12):
            raise ValueError("meshing: poisson_depth must be 0 (automatic) or lie in [4, 12]")
        if not (self.poisson_cell_m > 0 and 4 <= self.poisson_max_depth <= 12):
            raise ValueError("meshing: need poisson_cell_m > 0 and poisson_max_depth in [4, 12]")
        if not (self.threads == -1 or self.threads >= 1) or not (
                self.poisson_threads == -1 or self.poisson_threads >= 1):
            raise ValueError("meshing: threads and poisson_threads must be >= 1 (-1: every core)")
        if not 0 <= self.trim_density_quantile < 1:
            raise ValueError("meshing: trim_density_quantile must lie in [0, 1)")
        if self.min_component_samples < 0 or not 0 <= self.min_component_share < 1:
            raise ValueError("meshing: need min_component_samples >= 0 and "
                             "min_component_share in [0, 1)")


def _one_per_cell(points: FloatArray, cell_m: float, rng: np.random.Generator
                  ) -> NDArray[np.int64]:
    """Indices of one random point per occupied cubic cell."""
    order = rng.permutation(len(points))
    keys = pack_keys(np.floor(points[order] / cell_m).astype(np.int64))
    _, first = np.unique(keys, return_index=True)
    return np.asarray(order[first], dtype=np.int64)


def poisson_disk_indices(points: FloatArray, radius_m: float, seed: int = 0
                         ) -> NDArray[np.int64]:
    """Indices of a maximal Poisson-disk subset: pairwise >= radius_m, every point near one.

    Candidates (one per cell of radius/sqrt(3), so a cell never holds two samples) are
    reduced to a maximal independent set of the "closer than radius" graph by Luby's
    parallel algorithm: a candidate joins when its random priority beats all undecided
    neighbours', and its neighbours leave. Vectorised; a handful of rounds.
    """
    if len(points) == 0:
        return np.zeros(0, dtype=np.int64)
    rng = np.random.default_rng(seed)
    cand = _one_per_cell(points, radius_m / np.sqrt(3.0), rng)
    pairs = cKDTree(points[cand]).query_pairs(radius_m, output_type="ndarray")
    a = np.concatenate([pairs[:, 0], pairs[:, 1]])
    b = np.concatenate([pairs[:, 1], pairs[:, 0]])
    order = np.argsort(a, kind="stable")
    a, b = a[order], b[order]
    starts = np.flatnonzero(np.r_[True, a[1:] != a[:-1]]) if len(a) else a
    owners = a[starts]
    priority = rng.random(len(cand))
    state = np.zeros(len(cand), dtype=np.int8)  # 0 undecided, 1 chosen, -1 dropped
    while np.any(state == 0):
        # Highest priority among each candidate's undecided neighbours (segment maxima).
        best_neighbour = np.full(len(cand), -1.0)
        if len(a):
            live = np.where(state[b] == 0, priority[b], -1.0)
            best_neighbour[owners] = np.maximum.reduceat(live, starts)
        join = (state == 0) & (priority > best_neighbour)
        state[join] = 1
        near_join = join[a] & (state[b] == 0)
        state[b[near_join]] = -1
    return np.asarray(cand[state == 1], dtype=np.int64)


def _disk_means(points_world: FloatArray, normals_world: NDArray[np.float32],
                samples: FloatArray, config: MeshingConfig) -> tuple[FloatArray, FloatArray]:
    """Each sample moved along its normal to the mean of the points in a disk around it.

    The disk is one radius wide across the surface and two radii deep along the normal,
    so it holds the whole noise shell whichever side of it the sample was drawn from (a
    ball or a Voronoi cell centred on a noisy sample keeps that sample's offset).
    """
    r = config.sample_radius_m
    dist, near = cKDTree(points_world).query(
        samples, k=config.average_neighbours, distance_upper_bound=2.0 * r,
        workers=config.threads)
    found = np.isfinite(dist)
    near = np.where(found, near, 0)
    nsum = (normals_world[near].astype(np.float64) * found[..., None]).sum(axis=1)
    n = nsum / np.maximum(np.linalg.norm(nsum, axis=1, keepdims=True), 1e-12)
    offset = points_world[near] - samples[:, None, :]
    along = np.einsum("skc,sc->sk", offset, n)
    across = np.linalg.norm(offset - along[..., None] * n[:, None, :], axis=2)
    inside = found & (across <= r)
    count = np.maximum(inside.sum(axis=1), 1)
    shift = np.where(inside, along, 0.0).sum(axis=1) / count
    return samples + shift[:, None] * n, nsum


def poisson_disk_samples(points_world: FloatArray, normals_world: NDArray[np.float32],
                         config: MeshingConfig) -> tuple[FloatArray, FloatArray]:
    """(S, 3) Poisson-disk samples and their (S, 3) unit normals, metres."""
    idx = poisson_disk_indices(points_world, config.sample_radius_m, config.seed)
    samples = points_world[idx]
    normals = normals_world[idx].astype(np.float64)
    if config.average_samples and len(idx):
        samples, normals = _disk_means(points_world, normals_world, samples, config)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)
    return samples, normals


def _keep_faces(faces: NDArray[np.int32], keep_vertex: NDArray[np.bool_]
                ) -> NDArray[np.int32]:
    return faces[keep_vertex[faces].all(axis=1)]


def trim_distance(tree: cKDTree, config: MeshingConfig) -> float:
    """Distance from the samples beyond which the surface is cut, metres."""
    if tree.n < 2:
        return config.trim_distance_m
    spacing, _ = tree.query(tree.data, k=2, workers=config.threads)
    return max(config.trim_distance_m,
               config.trim_spacing_factor * float(np.median(spacing[:, 1])))


def poisson_depth(samples: FloatArray, config: MeshingConfig) -> int:
    """The octree depth of the solve: the configured one, or the automatic one."""
    if config.poisson_depth:
        return config.poisson_depth
    side = float(np.ptp(samples, axis=0).max()) * config.poisson_scale
    wanted = int(np.ceil(np.log2(max(side, 1e-9) / config.poisson_cell_m)))
    return int(np.clip(wanted, 4, config.poisson_max_depth))


def poisson_surface(samples: FloatArray, normals: FloatArray, config: MeshingConfig
                    ) -> tuple[FloatArray, NDArray[np.int32]]:
    """Screened Poisson surface of oriented samples, trimmed to where samples are."""
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(samples))
    cloud.normals = o3d.utility.Vector3dVector(normals)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh, density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
            cloud, depth=poisson_depth(samples, config), scale=config.poisson_scale,
            linear_fit=config.poisson_linear_fit, n_threads=config.poisson_threads)
    vertices = np.asarray(mesh.vertices)
    faces = np.asarray(mesh.triangles).astype(np.int32)
    density_arr = np.asarray(density)
    if len(vertices) == 0:
        return vertices, faces
    tree = cKDTree(samples)
    dist, _ = tree.query(vertices, workers=config.threads)
    trim_m = trim_distance(tree, config)
    keep = dist <= trim_m
    if config.trim_density_quantile > 0:
        keep &= density_arr >= np.quantile(density_arr, config.trim_density_quantile)
    vertices, faces = compact(vertices, _keep_faces(faces, keep))
    vertices, faces = drop_unsupported_components(vertices, faces, samples, trim_m, config)
    if config.min_component_share > 0:
        vertices, faces = drop_small_components(vertices, faces, config.min_component_share)
    return vertices, faces


def vertex_components(faces: NDArray[np.int32], vertex_count: int) -> NDArray[np.int64]:
    """(V,) connected-piece label of each vertex (vertices joined by the faces' edges)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    starts, ends = faces.ravel(), np.roll(faces, -1, axis=1).ravel()
    graph = coo_matrix((np.ones(len(starts), dtype=np.int8), (starts, ends)),
                       shape=(vertex_count, vertex_count))
    _, labels = connected_components(graph, directed=False)
    return np.asarray(labels, dtype=np.int64)


def drop_unsupported_components(vertices: FloatArray, faces: NDArray[np.int32],
                                samples: FloatArray, trim_m: float, config: MeshingConfig
                                ) -> tuple[FloatArray, NDArray[np.int32]]:
    """The mesh without the connected pieces that fewer than ``min_component_samples``
    samples lie on (a sample lies on the piece of its nearest vertex, within ``trim_m``)."""
    if len(faces) == 0 or config.min_component_samples == 0:
        return vertices, faces
    labels = vertex_components(faces, len(vertices))
    dist, nearest = cKDTree(vertices).query(samples, workers=config.threads)
    support = np.bincount(labels[nearest[dist <= trim_m]], minlength=int(labels.max()) + 1)
    keep_face = support[labels[faces[:, 0]]] >= config.min_component_samples
    return compact(vertices, faces[keep_face])


def mesh_cloud(points_world: FloatArray, normals_world: NDArray[np.float32],
               config: MeshingConfig) -> tuple[TriangleMesh, int]:
    """The surface of a refined, oriented cloud, and how many Poisson-disk samples it used."""
    if len(points_world) < 4:
        raise ValueError("points_world: too few points to mesh (is the subject in view?)")
    samples, normals = poisson_disk_samples(points_world, normals_world, config)
    vertices, faces = poisson_surface(samples, normals, config)
    if len(faces) == 0:
        raise ValueError("points_world: the surface reconstruction produced no triangles")
    return TriangleMesh(vertices_m=vertices, faces=faces), len(samples)
