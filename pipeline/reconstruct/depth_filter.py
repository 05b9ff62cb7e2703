"""Depth processing: range limits, flying-pixel removal, bilateral filtering.

All functions take and return ``depth_m``: (H, W) float32 metres along the camera's z axis,
0 where there is no measurement. They never invent depth where there was none.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

DepthImage = NDArray[np.float32]


@dataclass(frozen=True)
class DepthFilterConfig:
    """How raw depth images are cleaned before back-projection."""

    min_depth_m: float = 0.25
    """Depths nearer than this are dropped (Azure Kinect NFOV starts at about 0.5 m)."""
    max_depth_m: float = 5.5
    """Depths farther than this are dropped (beyond the sensor's working range)."""
    flying_ratio: float = 4.0
    """A pixel is a flying pixel when its depth jumps from a valid neighbour's by more than
    this many times the footprint of one pixel at that depth (depth / focal length), i.e.
    the surface would be steeper than about atan(flying_ratio) against the view."""
    flying_min_jump_m: float = 0.01
    """Jumps below this are never flying pixels, whatever the footprint (noise floor)."""
    flying_noise_factor: float = 5.0
    """Jumps within this many times the local depth noise (`local_noise_m`) are noise, never
    flying pixels (0: off). A far or structured-light surface jumps by centimetres between
    neighbours all over; on a clean surface the noise is a millimetre and a mixed pixel's
    jump stands out."""
    isolated_min_neighbours: int = 3
    """Pixels with fewer valid 8-neighbours than this are dropped as speckles."""
    bilateral_radius_px: int = 2
    """Half-width of the bilateral window in pixels (0 disables the bilateral filter)."""
    bilateral_sigma_px: float = 1.5
    """Spatial standard deviation of the bilateral weights, pixels."""
    bilateral_sigma_m: float = 0.003
    """Range standard deviation of the bilateral weights at 1 m, metres."""
    bilateral_sigma_per_m: float = 0.002
    """Growth of the range standard deviation per metre of depth (noise grows with depth)."""
    erode_edges_px: int = 0
    """Valid pixels this close to an invalid one are dropped after flying-pixel removal:
    depth there mixes foreground and background."""

    def __post_init__(self) -> None:
        if not 0 <= self.min_depth_m < self.max_depth_m:
            raise ValueError("depth_filter: need 0 <= min_depth_m < max_depth_m")
        if self.bilateral_radius_px < 0 or self.erode_edges_px < 0:
            raise ValueError("depth_filter: radii must be >= 0")
        if self.bilateral_sigma_px <= 0 or self.bilateral_sigma_m <= 0:
            raise ValueError("depth_filter: bilateral sigmas must be > 0")
        if self.flying_ratio <= 0:
            raise ValueError("depth_filter: flying_ratio must be > 0")
        if self.flying_noise_factor < 0:
            raise ValueError("depth_filter: flying_noise_factor must be >= 0")


def _shifted(image: NDArray[np.float32], dy: int, dx: int) -> NDArray[np.float32]:
    """image shifted so that out[y, x] = image[y + dy, x + dx]; 0 outside the image."""
    h, w = image.shape
    out = np.zeros_like(image)
    ys, yd = (slice(dy, h), slice(0, h - dy)) if dy >= 0 else (slice(0, h + dy), slice(-dy, h))
    xs, xd = (slice(dx, w), slice(0, w - dx)) if dx >= 0 else (slice(0, w + dx), slice(-dx, w))
    out[yd, xd] = image[ys, xs]
    return out


def _neighbour_offsets(radius: int) -> list[tuple[int, int]]:
    return [(dy, dx) for dy in range(-radius, radius + 1) for dx in range(-radius, radius + 1)
            if (dy, dx) != (0, 0)]


def apply_range(depth_m: DepthImage, config: DepthFilterConfig) -> DepthImage:
    """Zero the depths outside [min_depth_m, max_depth_m] and any non-finite value."""
    depth = np.nan_to_num(depth_m.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    keep = (depth >= config.min_depth_m) & (depth <= config.max_depth_m)
    return np.where(keep, depth, np.float32(0.0))


_SECOND_DIFFERENCE_PER_SIGMA = 2.34
"""Median, over Gaussian noise of unit deviation, of the larger of a pixel's second
differences along x and y (measured)."""
_NOISE_WINDOW = 5
"""Side of the median's window on the grid of every second pixel (about 10 pixels)."""


def local_noise_m(depth_m: DepthImage) -> DepthImage:
    """(H, W) standard deviation of the depth noise around each pixel, metres.

    Second differences cancel a slope. Their median over a window about 10 pixels wide
    ignores an edge, and the mixed pixels along it, which reach a third of the window at
    most; a noisy or quantised surface jumps all over the window and raises it. The
    median runs on every second pixel (four times cheaper; noise is not that local). A
    difference that needs an invalid pixel counts as 0, so the estimate errs low (towards
    the plain jump limit) where depth is sparse.
    """
    padded = np.pad(depth_m.astype(np.float32), 1)
    centre = padded[1:-1:2, 1:-1:2]
    second = np.zeros(centre.shape, dtype=np.float32)
    for ahead, behind in ((padded[1:-1:2, 2::2], padded[1:-1:2, 0:-2:2]),
                          (padded[2::2, 1:-1:2], padded[0:-2:2, 1:-1:2])):
        both = (centre > 0) & (ahead > 0) & (behind > 0)
        second = np.maximum(second, np.where(both, np.abs(ahead - 2 * centre + behind),
                                             np.float32(0.0)))
    coarse = cv2.medianBlur(second, _NOISE_WINDOW)
    height, width = depth_m.shape
    full = np.repeat(np.repeat(coarse, 2, axis=0), 2, axis=1)[:height, :width]
    return (full / np.float32(_SECOND_DIFFERENCE_PER_SIGMA)).astype(np.float32)


def remove_flying_pixels(depth_m: DepthImage, focal_px: float,
                         config: DepthFilterConfig) -> DepthImage:
    """Drop pixels at depth edges whose depth jumps from a valid neighbour's too steeply.

    Flying pixels mix foreground and background returns; they sit on the steep side of a
    jump, so the farther pixel of each too-steep pair is dropped (the silhouette of the
    nearer surface stays), then ``erode_edges_px`` more pixels are trimmed at holes. A jump
    is too steep beyond ``flying_ratio`` footprints and beyond the local noise.
    """
    depth = depth_m.astype(np.float32)
    valid = depth > 0
    footprint = depth / np.float32(focal_px)
    limit = np.maximum(config.flying_ratio * footprint, config.flying_min_jump_m)
    if config.flying_noise_factor > 0:
        limit = np.maximum(limit, np.float32(config.flying_noise_factor)
                           * local_noise_m(depth))
    flying = np.zeros(depth.shape, dtype=bool)
    neighbours = np.zeros(depth.shape, dtype=np.int32)
    for dy, dx in _neighbour_offsets(1):
        other = _shifted(depth, dy, dx)
        other_valid = other > 0
        neighbours += other_valid
        flying |= valid & other_valid & (depth - other > limit * np.float32(np.hypot(dy, dx)))
    keep = valid & ~flying & (neighbours >= config.isolated_min_neighbours)
    for _ in range(config.erode_edges_px):
        inner = keep.copy()
        for dy, dx in _neighbour_offsets(1):
            inner &= _shifted(keep.astype(np.float32), dy, dx) > 0
        keep = inner
    return np.where(keep, depth, np.float32(0.0))


def bilateral(depth_m: DepthImage, config: DepthFilterConfig) -> DepthImage:
    """Edge-preserving smoothing in metres; invalid pixels neither receive nor give depth.

    The range sigma grows with depth like the sensor's noise, so near and far surfaces are
    smoothed alike relative to their noise, while steps larger than a few sigma stay sharp.
    """
    radius = config.bilateral_radius_px
    depth = depth_m.astype(np.float32)
    if radius == 0:
        return depth
    valid = depth > 0
    sigma_m = np.float32(config.bilateral_sigma_m) + np.float32(
        config.bilateral_sigma_per_m) * np.maximum(depth - np.float32(1.0), np.float32(0.0))
    inv_two_var = np.float32(-0.5) / (sigma_m * sigma_m)
    total = depth.copy()
    weight = valid.astype(np.float32)
    two_var_px = 2.0 * config.bilateral_sigma_px**2
    for dy, dx in _neighbour_offsets(radius):
        spatial = np.float32(np.exp(-(dy * dy + dx * dx) / two_var_px))
        other = _shifted(depth, dy, dx)
        diff = other - depth
        w = np.exp(diff * diff * inv_two_var) * spatial
        w *= other > 0
        total += w * other
        weight += w
    out = np.divide(total, weight, out=np.zeros_like(total), where=weight > 0)
    return np.where(valid, out, np.float32(0.0)).astype(np.float32)


def filter_depth(depth_m: DepthImage, focal_px: float, config: DepthFilterConfig) -> DepthImage:
    """The whole depth clean-up: range limits, flying pixels, then bilateral smoothing."""
    if depth_m.ndim != 2:
        raise ValueError(f"depth_m: expected an (H, W) image, got shape {depth_m.shape}")
    if not focal_px > 0:
        raise ValueError("focal_px: must be > 0")
    depth = apply_range(depth_m, config)
    depth = remove_flying_pixels(depth, focal_px, config)
    return bilateral(depth, config)
