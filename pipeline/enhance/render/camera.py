"""The orthographic cameras and render types that both depth renderers share.

Depth is normalised per view so one model serves any scale: a view's image covers the bounding
sphere (radius R, times a margin) and depth 0..1 spans the sphere's depth range 2R·margin from
the plane that touches its near side. Cameras follow OpenCV (x right, y down, z forward).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

_AXIS_FORWARDS = np.array(
    [
        [0.0, 0.0, -1.0],  # front: camera on +Z looking back at the subject
        [1.0, 0.0, 0.0],  # left: camera on -X
        [0.0, 0.0, 1.0],  # back
        [-1.0, 0.0, 0.0],  # right
        [0.0, -1.0, 0.0],  # top: camera above, looking down
        [0.0, 1.0, 0.0],  # bottom
    ]
)


@dataclass(frozen=True)
class ViewSet:
    """Orthographic cameras around a bounding sphere."""

    forwards: NDArray[np.float64]
    """(N, 3) unit viewing directions (camera +z) in the mesh's frame."""
    rights: NDArray[np.float64]
    """(N, 3) unit camera +x axes."""
    downs: NDArray[np.float64]
    """(N, 3) unit camera +y axes."""
    center_m: NDArray[np.float64]
    """(3,) bounding-sphere centre, metres."""
    half_extent_m: float
    """Half the image side and half the depth range (sphere radius times margin), metres."""
    resolution: int
    """Image side in pixels (images are square)."""

    @property
    def count(self) -> int:
        return int(self.forwards.shape[0])

    @property
    def depth_range_m(self) -> float:
        """Metres per unit of normalised depth."""
        return 2.0 * self.half_extent_m


@dataclass(frozen=True)
class DepthRenders:
    """Normalised depth images (and optional colour) of one mesh."""

    views: ViewSet
    depth_n: NDArray[np.float32]
    """(N, H, W) normalised depth in [0, 1]; 1 where nothing was hit."""
    valid: NDArray[np.bool_]
    """(N, H, W) True where a ray hit the surface."""
    color_rgb: NDArray[np.uint8] | None = None
    """(N, H, W, 3) interpolated vertex colours, or None when the mesh has none."""


def view_directions(count: int) -> NDArray[np.float64]:
    """(count, 3) viewing directions: the six axis views first, then evenly spread extras."""
    if count < 1:
        raise ValueError(f"views must be at least 1, got {count}")
    if count <= 6:
        return _AXIS_FORWARDS[:count].copy()
    extra = count - 6
    # A Fibonacci spiral spreads the extra views; offset so none repeats an axis view exactly.
    k = np.arange(extra) + 0.5
    z = 1.0 - 2.0 * k / extra
    phi = k * np.pi * (3.0 - np.sqrt(5.0)) + 0.3
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, 1.0))
    spiral = np.stack([r * np.cos(phi), z, r * np.sin(phi)], axis=1)
    return np.concatenate([_AXIS_FORWARDS, spiral], axis=0)


def make_views(
    vertices_m: NDArray[np.float64],
    forwards: NDArray[np.float64],
    resolution: int,
    margin: float = 1.05,
) -> ViewSet:
    """Cameras looking along `forwards` (N, 3) at the bounding sphere of `vertices_m` (V, 3)."""
    if resolution < 8:
        raise ValueError(f"resolution must be at least 8 pixels, got {resolution}")
    if len(vertices_m) == 0:
        raise ValueError("mesh has no vertices")
    center = 0.5 * (vertices_m.min(axis=0) + vertices_m.max(axis=0))
    radius = float(np.linalg.norm(vertices_m - center, axis=1).max())
    if radius <= 0:
        raise ValueError("mesh is degenerate: all vertices coincide")
    fwd = forwards / np.linalg.norm(forwards, axis=1, keepdims=True)
    up = np.tile(np.array([0.0, 1.0, 0.0]), (len(fwd), 1))
    # Looking straight up or down, "up" in the image is the world's -Z (front is down).
    vertical = np.abs(fwd[:, 1]) > 0.95
    up[vertical] = np.array([0.0, 0.0, -1.0]) * np.sign(-fwd[vertical, 1])[:, None]
    down = -(up - np.sum(up * fwd, axis=1, keepdims=True) * fwd)
    down /= np.linalg.norm(down, axis=1, keepdims=True)
    right = np.cross(down, fwd)
    return ViewSet(fwd, right, down, center, radius * margin, resolution)


def project(points_m: NDArray[np.float64], views: ViewSet) -> tuple[NDArray, NDArray]:
    """Pixel coordinates (N, P, 2) as (column, row), continuous, and normalised depth (N, P)."""
    rel = points_m[None, :, :] - views.center_m[None, None, :]
    x = np.einsum("npk,nk->np", rel, views.rights)
    y = np.einsum("npk,nk->np", rel, views.downs)
    z = np.einsum("npk,nk->np", rel, views.forwards)
    scale = views.resolution / (2.0 * views.half_extent_m)
    cols = (x + views.half_extent_m) * scale - 0.5
    rows = (y + views.half_extent_m) * scale - 0.5
    depth_n = (z + views.half_extent_m) / views.depth_range_m
    return np.stack([cols, rows], axis=-1), depth_n
