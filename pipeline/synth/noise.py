"""An Azure Kinect (NFOV unbinned) depth noise model for synthetic captures.

Figures used and where they come from:

* Operating range 0.5-3.86 m, NFOV unbinned (Azure Kinect DK hardware specification,
  "Depth camera supported operating modes"); outside it the sensor reports 0.
* Random error: the specification bounds its standard deviation by 17 mm; measured values are
  far lower, about 1 mm at 1 m growing roughly linearly with distance (Tölgyessy et al.,
  "Evaluation of the Azure Kinect and its comparison to Kinect V1 and Kinect V2", Sensors
  21(2):413, 2021). We use sigma = 0.5 mm + 1 mm per metre beyond 0.5 m, along the ray.
* Systematic error: specified below 11 mm + 0.1 % of distance; after warm-up a single unit
  shows a near-constant offset of a few millimetres (Tölgyessy et al.). We draw one offset per
  camera, Gaussian with a 2 mm standard deviation by default.
* Depth is reported in whole millimetres (16-bit, 1 mm per unit).
* Invalid pixels: the depth engine invalidates pixels with too low an IR return, which is what
  surfaces seen at grazing angles give (Lambertian return falls with the cosine of incidence),
  and mixed pixels at depth discontinuities ("Azure Kinect depth camera" docs, invalidation);
  some mixed pixels survive as "flying pixels" between foreground and background.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from pipeline.capture import Intrinsics


@dataclass(frozen=True)
class KinectNoiseConfig:
    """Parameters of the noise model; the defaults follow the Azure Kinect NFOV unbinned mode."""

    sigma_base_m: float = 0.0005
    """Random depth error standard deviation at `sigma_ref_m` and nearer, metres."""
    sigma_per_m: float = 0.001
    """Growth of the standard deviation per metre of distance beyond `sigma_ref_m`."""
    sigma_ref_m: float = 0.5
    """Distance where the standard deviation is `sigma_base_m`, metres."""
    bias_std_m: float = 0.002
    """Standard deviation of the constant per-camera depth offset, metres (a few mm)."""
    quantization_m: float = 0.001
    """Depth resolution of the reported values, metres (0 disables rounding)."""
    min_range_m: float = 0.5
    """Nearest depth the sensor reports, metres."""
    max_range_m: float = 3.86
    """Farthest depth the sensor reports, metres."""
    invalid_fraction: float = 0.002
    """Fraction of pixels dropped at random (speckle of invalid pixels)."""
    grazing_cos_start: float = 0.26
    """Cosine of incidence below which dropouts begin (about 75 degrees)."""
    grazing_cos_full: float = 0.1
    """Cosine of incidence below which every pixel is dropped (about 84 degrees)."""
    edge_jump_m: float = 0.05
    """Depth step to a 4-neighbour that makes a pixel a depth-edge (mixed) pixel, metres."""
    edge_invalid_fraction: float = 0.5
    """Fraction of depth-edge pixels the sensor invalidates."""
    flying_fraction: float = 0.35
    """Fraction of depth-edge pixels that report a mix of both depths (flying pixels)."""
    background_m: float | None = 4.5
    """Depth assumed behind silhouettes (studio walls beyond range, so misses stay 0), metres;
    None: misses mix with nothing and silhouettes make no flying pixels."""

    def __post_init__(self) -> None:
        fractions = ("invalid_fraction", "edge_invalid_fraction", "flying_fraction")
        for name in fractions:
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name}: must lie in [0, 1]")
        if self.edge_invalid_fraction + self.flying_fraction > 1.0:
            raise ValueError("edge_invalid_fraction + flying_fraction: must not exceed 1")
        if not 0.0 <= self.grazing_cos_full <= self.grazing_cos_start <= 1.0:
            raise ValueError("grazing_cos_full/start: need 0 <= full <= start <= 1")
        if not 0.0 <= self.min_range_m < self.max_range_m:
            raise ValueError("min_range_m/max_range_m: need 0 <= min < max")
        for name in ("sigma_base_m", "sigma_per_m", "bias_std_m", "quantization_m"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name}: must not be negative")

    def sigma_m(self, distance_m: NDArray[np.floating] | float) -> NDArray[np.float64]:
        """Standard deviation of the random error along the ray at `distance_m`, metres."""
        excess = np.maximum(np.asarray(distance_m, dtype=np.float64) - self.sigma_ref_m, 0.0)
        return self.sigma_base_m + self.sigma_per_m * excess


def draw_depth_bias_m(config: KinectNoiseConfig, rng: np.random.Generator) -> float:
    """One camera's constant depth offset along its rays, metres."""
    return float(rng.normal(0.0, config.bias_std_m)) if config.bias_std_m > 0 else 0.0


def apply_kinect_noise(depth_m: NDArray[np.floating], normals_cam: NDArray[np.floating] | None,
                       intrinsics: Intrinsics, config: KinectNoiseConfig,
                       rng: np.random.Generator, bias_m: float = 0.0) -> NDArray[np.float32]:
    """A noisy sensor reading of an ideal z-depth image.

    depth_m: (H, W) ideal z-depth, metres, 0 = nothing hit. normals_cam: (H, W, 3) unit
    surface normals in the camera frame (None: no grazing-angle dropouts). bias_m: this
    camera's offset from `draw_depth_bias_m`. Returns (H, W) float32 metres, 0 = invalid.
    """
    depth = np.asarray(depth_m, dtype=np.float64)
    if depth.shape != (intrinsics.height, intrinsics.width):
        raise ValueError(f"depth_m: shape {depth.shape} does not match the intrinsics "
                         f"{intrinsics.height}x{intrinsics.width}")
    # |ray| per unit z: the sensor measures along the ray, the image stores z.
    u = (np.arange(intrinsics.width) - intrinsics.cx) / intrinsics.fx
    v = (np.arange(intrinsics.height) - intrinsics.cy) / intrinsics.fy
    ray_scale = np.sqrt(1.0 + u[None, :] ** 2 + v[:, None] ** 2)
    surface = depth > 0
    keep = rng.random(depth.shape) >= config.invalid_fraction
    if normals_cam is not None:
        # Only real surfaces have an incidence angle; blends from the background do not.
        keep &= _survives_grazing(np.asarray(normals_cam), u, v, config, rng) | ~surface
    depth, valid = _mixed_pixels(depth, surface, config, rng)
    distance = depth * ray_scale
    error = bias_m + rng.normal(size=depth.shape) * config.sigma_m(distance)
    noisy = depth + error / ray_scale
    keep &= valid
    if config.quantization_m > 0:
        noisy = np.rint(noisy / config.quantization_m) * config.quantization_m
    keep &= (noisy >= config.min_range_m) & (noisy <= config.max_range_m)
    return np.where(keep, noisy, 0.0).astype(np.float32)


def _mixed_pixels(depth: NDArray[np.float64], valid: NDArray[np.bool_],
                  config: KinectNoiseConfig, rng: np.random.Generator
                  ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Depth-edge pixels: some invalidated, some turned into a blend of both sides."""
    if config.background_m is None:
        seen = np.where(valid, depth, np.nan)
    else:
        seen = np.where(valid, depth, config.background_m)
    other = np.full(depth.shape, np.nan)
    jump = np.zeros(depth.shape)
    padded = np.pad(seen, 1, constant_values=np.nan)
    height, width = depth.shape
    for dy, dx in ((0, 1), (2, 1), (1, 0), (1, 2)):
        neighbour = padded[dy:dy + height, dx:dx + width]
        step = np.abs(neighbour - seen)
        larger = np.nan_to_num(step, nan=0.0) > jump
        jump = np.where(larger, step, jump)
        other = np.where(larger, neighbour, other)
    # A pixel straddles the edge when it or its neighbour is a real surface.
    edge = (jump > config.edge_jump_m) & np.isfinite(seen)
    draw = rng.random(depth.shape)
    dropped = edge & (draw < config.edge_invalid_fraction)
    flying = edge & ~dropped & (draw < config.edge_invalid_fraction + config.flying_fraction)
    # The pixel's footprint covers a fraction c of its own surface; each return is weighted
    # by its strength, which falls with the square of distance.
    c = rng.random(depth.shape)
    own, far = np.where(flying, seen, 1.0), np.where(flying, other, 1.0)
    w_own = c / own**2
    w_far = (1.0 - c) / far**2
    blend = (w_own * own + w_far * far) / (w_own + w_far)
    out = np.where(flying, blend, depth)
    out_valid = (valid | flying) & ~dropped
    return out, out_valid


def _survives_grazing(normals_cam: NDArray[np.floating], u: NDArray[np.floating],
                      v: NDArray[np.floating], config: KinectNoiseConfig,
                      rng: np.random.Generator) -> NDArray[np.bool_]:
    """True where the IR return at this incidence angle is strong enough to keep the pixel."""
    rays = np.stack(np.broadcast_arrays(u[None, :], v[:, None], np.ones(1)), axis=-1)
    rays = rays / np.linalg.norm(rays, axis=-1, keepdims=True)
    cos_incidence = np.abs(np.sum(rays * normals_cam, axis=-1))
    span = config.grazing_cos_start - config.grazing_cos_full
    if span <= 0:
        drop_p = (cos_incidence < config.grazing_cos_full).astype(np.float64)
    else:
        drop_p = np.clip((config.grazing_cos_start - cos_incidence) / span, 0.0, 1.0)
    return rng.random(cos_incidence.shape) >= drop_p
