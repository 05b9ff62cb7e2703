"""Voxel refinement: one camera per voxel, continuous across each layer.

Depth error grows with distance, so in each voxel only the points of the camera nearest to
that voxel are kept (among the cameras with points there). A nearest-camera choice flips
wherever two cameras are about equally near, which leaves seams of alternating cameras;
so, layer by layer along ``layer_axis``, each voxel then takes the camera chosen most often
among its 8 neighbours in the same layer, among the cameras that have points in the voxel.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

IntArray = NDArray[np.int64]

# Keys pack three voxel coordinates of 21 bits each into one int64.
_BITS = 21
_LIMIT = 1 << _BITS


@dataclass(frozen=True)
class VoxelRefineConfig:
    """How the world is cut into voxels and how cameras are chosen per voxel."""

    voxel_size_m: float = 0.006
    """Edge of a voxel, metres."""
    layer_axis: int = 2
    """World axis (0 x, 1 y, 2 z) across which the layers of the majority step are cut;
    the 8 neighbours of a voxel vary along the two other axes."""
    majority_passes: int = 1
    """How many times the 8-neighbour majority step runs (0 disables it)."""

    def __post_init__(self) -> None:
        if not self.voxel_size_m > 0:
            raise ValueError("voxel_refine: voxel_size_m must be > 0")
        if self.layer_axis not in (0, 1, 2):
            raise ValueError("voxel_refine: layer_axis must be 0, 1 or 2")
        if self.majority_passes < 0:
            raise ValueError("voxel_refine: majority_passes must be >= 0")


@dataclass(frozen=True)
class VoxelChoice:
    """The voxels of a cloud and the camera chosen for each."""

    coords: IntArray
    """(V, 3) integer voxel coordinates, sorted by key."""
    keys: IntArray
    """(V,) packed, sorted keys of ``coords``."""
    present: NDArray[np.bool_]
    """(V, C) whether camera c has points in voxel v."""
    camera: IntArray
    """(V,) index of the camera chosen for each voxel."""
    point_voxel: IntArray
    """(N,) voxel index of every input point."""


def pack_keys(coords: IntArray) -> IntArray:
    """(V,) int64 keys of (V, 3) voxel coordinates (each in [-2^20, 2^20))."""
    shifted = coords + (_LIMIT // 2)
    if shifted.size and (shifted.min() < 0 or shifted.max() >= _LIMIT):
        raise ValueError("points_world: the cloud spans too many voxels for voxel_size_m")
    return (shifted[:, 0] << (2 * _BITS)) | (shifted[:, 1] << _BITS) | shifted[:, 2]


def nearest_camera(coords: IntArray, present: NDArray[np.bool_],
                   camera_centers_world: NDArray[np.float64], voxel_size_m: float) -> IntArray:
    """(V,) for each voxel, the present camera whose centre is nearest the voxel's centre."""
    centres = (coords.astype(np.float64) + 0.5) * voxel_size_m
    dist = np.full(present.shape, np.inf)
    for c, centre in enumerate(camera_centers_world):
        rows = np.nonzero(present[:, c])[0]
        dist[rows, c] = np.sum((centres[rows] - centre) ** 2, axis=1)
    return np.argmin(dist, axis=1).astype(np.int64)


def _layer_offsets(layer_axis: int) -> IntArray:
    in_plane = [a for a in range(3) if a != layer_axis]
    offsets = []
    for du in (-1, 0, 1):
        for dv in (-1, 0, 1):
            if du == 0 and dv == 0:
                continue
            off = np.zeros(3, dtype=np.int64)
            off[in_plane[0]], off[in_plane[1]] = du, dv
            offsets.append(off)
    return np.array(offsets)


def neighbour_votes(coords: IntArray, keys: IntArray, camera: IntArray, camera_count: int,
                    layer_axis: int) -> IntArray:
    """(V, C) how many of each voxel's 8 same-layer neighbours chose camera c."""
    votes = np.zeros(len(keys) * camera_count, dtype=np.int64)
    for off in _layer_offsets(layer_axis):
        neighbour_keys = pack_keys(coords + off)
        idx = np.searchsorted(keys, neighbour_keys)
        idx = np.minimum(idx, len(keys) - 1)
        found = keys[idx] == neighbour_keys
        rows = np.nonzero(found)[0]
        votes += np.bincount(rows * camera_count + camera[idx[found]],
                             minlength=len(votes))
    return votes.reshape(len(keys), camera_count)


def majority_step(coords: IntArray, keys: IntArray, present: NDArray[np.bool_],
                  camera: IntArray, layer_axis: int) -> IntArray:
    """(V,) each voxel's camera after one 8-neighbour majority vote within its layer.

    Only cameras with points in the voxel can win; ties keep the voxel's own choice when it
    is among the tied, and voxels with no voting neighbour keep theirs.
    """
    camera_count = present.shape[1]
    votes = neighbour_votes(coords, keys, camera, camera_count, layer_axis)
    votes = np.where(present, votes, -1)
    best = votes.max(axis=1)
    own = votes[np.arange(len(camera)), camera]
    winner = np.argmax(votes, axis=1)
    keep_own = (own >= best) | (best <= 0)
    return np.where(keep_own, camera, winner).astype(np.int64)


def choose_cameras(points_world: NDArray[np.float64], camera_index: IntArray,
                   camera_centers_world: NDArray[np.float64],
                   config: VoxelRefineConfig) -> VoxelChoice:
    """Voxelise the cloud and choose one camera per voxel (nearest, then majority)."""
    if points_world.ndim != 2 or points_world.shape[1] != 3:
        raise ValueError(f"points_world: expected (N, 3), got {points_world.shape}")
    if camera_index.shape != (len(points_world),):
        raise ValueError("camera_index: expected one camera index per point")
    camera_count = len(camera_centers_world)
    if len(camera_index) and (camera_index.min() < 0 or camera_index.max() >= camera_count):
        raise ValueError("camera_index: indices must lie in [0, number of cameras)")
    point_coords = np.floor(points_world / config.voxel_size_m).astype(np.int64)
    point_keys = pack_keys(point_coords)
    keys, first, point_voxel = np.unique(point_keys, return_index=True, return_inverse=True)
    coords = point_coords[first]
    present = np.zeros((len(keys), camera_count), dtype=bool)
    present[point_voxel, camera_index] = True
    camera = nearest_camera(coords, present, camera_centers_world, config.voxel_size_m)
    for _ in range(config.majority_passes):
        camera = majority_step(coords, keys, present, camera, config.layer_axis)
    return VoxelChoice(coords=coords, keys=keys, present=present, camera=camera,
                       point_voxel=point_voxel.astype(np.int64))


def refine_mask(points_world: NDArray[np.float64], camera_index: IntArray,
                camera_centers_world: NDArray[np.float64],
                config: VoxelRefineConfig) -> NDArray[np.bool_]:
    """(N,) True for the points that the voxel refinement keeps."""
    if len(points_world) == 0:
        return np.zeros(0, dtype=bool)
    choice = choose_cameras(points_world, camera_index, camera_centers_world, config)
    return np.asarray(choice.camera[choice.point_voxel] == camera_index)
