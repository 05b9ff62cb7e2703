"""Cropping registered points to the subject: the rig's inner volume, minus the floor and
stray points.

Real captures see the studio too: walls and far objects beyond the ring of cameras, and the
floor under the subject. Both would be meshed along with the subject (a floor plane of a
few square metres costs more than the subject). The world is +Y up (docs/architecture.md), so
the floor is found as the lowest dense layer of up-facing points with (almost) nothing below
it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from pipeline.reconstruct.voxel_refine import pack_keys

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class CropConfig:
    """What is cut away before refinement."""

    enabled: bool = True
    """Crop at all (False keeps every registered point)."""
    radius_factor: float = 0.95
    """Points farther from the rig's vertical axis (where the cameras look, seen from above)
    than this share of the nearest camera's horizontal distance to it are dropped."""
    remove_floor: bool = True
    """Detect a floor under the subject and drop it."""
    floor_normal_cos: float = 0.9
    """Points whose normal is within acos(this) of +Y face up (floor candidates)."""
    floor_bin_m: float = 0.01
    """Height bins in which the floor layer is sought, metres."""
    floor_min_share: float = 0.05
    """A floor layer holds at least this share of all points."""
    floor_max_below_share: float = 0.01
    """...and at most this share of all points lies below it (a table top is not a floor)."""
    floor_margin_m: float = 0.01
    """Points up to this far above the floor layer are dropped with it, metres."""
    speckle_cell_m: float = 0.02
    """Cells of at least this size, metres, and at least ``speckle_cell_spacings`` point
    spacings, in which stray points are counted..."""
    speckle_cell_spacings: float = 5.0
    """...(so a seen surface puts some 20 or more points in each cell)..."""
    speckle_min_points: int = 2
    """...and points in cells holding fewer than this many are dropped: the floor's noise
    above the margin and leftover flying pixels are alone in their cells; sparse but real
    surfaces (seen obliquely) rarely are."""

    def __post_init__(self) -> None:
        if not self.radius_factor > 0 or not self.floor_bin_m > 0:
            raise ValueError("crop: radius_factor and floor_bin_m must be > 0")
        if not 0 < self.floor_min_share < 1 or not 0 <= self.floor_max_below_share < 1:
            raise ValueError("crop: floor shares must lie in (0, 1)")


def rig_axis(world_from_depth: list[FloatArray]) -> tuple[FloatArray, float] | None:
    """(x, z) of the vertical axis the cameras look at, and the nearest camera's horizontal
    distance to it; None unless at least three cameras surround it (no gap of 180 degrees
    or more between their directions from it)."""
    if len(world_from_depth) < 3:
        return None
    centres = np.array([pose[[0, 2], 3] for pose in world_from_depth])
    views = np.array([pose[[0, 2], 2] for pose in world_from_depth])
    length = np.linalg.norm(views, axis=1)
    if np.any(length < 1e-6):
        return None  # a camera looking straight up or down
    views /= length[:, None]
    # Least-squares meeting point of the optical axes seen from above.
    projectors = np.eye(2)[None] - views[:, :, None] * views[:, None, :]
    lhs, rhs = projectors.sum(axis=0), np.einsum("kij,kj->i", projectors, centres)
    if np.linalg.cond(lhs) > 1e6:
        return None
    axis = np.linalg.solve(lhs, rhs)
    offsets = centres - axis
    azimuths = np.sort(np.arctan2(offsets[:, 1], offsets[:, 0]))
    gaps = np.diff(np.r_[azimuths, azimuths[0] + 2 * np.pi])
    if gaps.max() >= np.pi:
        return None
    return axis, float(np.linalg.norm(offsets, axis=1).min())


def rig_cylinder_mask(points_world: FloatArray, world_from_depth: list[FloatArray],
                      radius_factor: float) -> NDArray[np.bool_]:
    """(N,) points inside the vertical cylinder the cameras stand around (all points when
    they do not surround one)."""
    found = rig_axis(world_from_depth)
    if found is None:
        return np.ones(len(points_world), dtype=bool)
    axis, distance = found
    return np.asarray(np.linalg.norm(points_world[:, [0, 2]] - axis, axis=1)
                      < radius_factor * distance)


def find_floor(points_world: FloatArray, normals_world: NDArray[np.float32],
               config: CropConfig) -> float | None:
    """Height (y, metres) of a floor layer under everything else, or None."""
    if len(points_world) == 0:
        return None
    y = points_world[:, 1]
    up = normals_world[:, 1] >= config.floor_normal_cos
    if not up.any():
        return None
    low = float(y.min())
    bins = np.floor((y[up] - low) / config.floor_bin_m).astype(np.int64)
    counts = np.bincount(bins)
    dense = np.flatnonzero(counts >= config.floor_min_share * len(y))
    if len(dense) == 0:
        return None
    floor_y = low + (dense[0] + 0.5) * config.floor_bin_m
    below = np.count_nonzero(y < floor_y - config.floor_bin_m)
    return floor_y if below <= config.floor_max_below_share * len(y) else None


def crop_mask(points_world: FloatArray, normals_world: NDArray[np.float32],
              world_from_depth: list[FloatArray], spacing_m: float, config: CropConfig
              ) -> tuple[NDArray[np.bool_], float | None]:
    """(N,) points kept, and the floor height found (None: no floor).

    spacing_m: typical distance between neighbouring points (a pixel's footprint), metres.
    """
    keep = np.ones(len(points_world), dtype=bool)
    if not config.enabled:
        return keep, None
    keep &= rig_cylinder_mask(points_world, world_from_depth, config.radius_factor)
    floor_y = None
    if config.remove_floor:
        floor_y = find_floor(points_world[keep], normals_world[keep], config)
        if floor_y is not None:
            keep &= points_world[:, 1] > floor_y + config.floor_margin_m
    if config.speckle_min_points > 1:
        idx = np.flatnonzero(keep)
        cell = max(config.speckle_cell_m, config.speckle_cell_spacings * spacing_m)
        keep[idx[sparse_mask(points_world[idx], cell, config.speckle_min_points)]] = False
    return keep, floor_y


def sparse_mask(points_world: FloatArray, cell_m: float, min_points: int
                ) -> NDArray[np.bool_]:
    """(N,) points lying in cubic cells that hold fewer than min_points points."""
    if len(points_world) == 0:
        return np.zeros(0, dtype=bool)
    cells = pack_keys(np.floor(points_world / cell_m).astype(np.int64))
    _, inverse, counts = np.unique(cells, return_inverse=True, return_counts=True)
    return np.asarray(counts[inverse] < min_points)
