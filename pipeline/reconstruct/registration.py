"""Registration: depth pixels back-projected and moved into the world frame.

Camera frames are OpenCV's (x right, y down, z forward); the world is metres, +Y up.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from pipeline.capture import Intrinsics

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class RegistrationConfig:
    """How depth pixels become oriented world points."""

    normal_step_px: int = 2
    """Pixel step of the central differences that give per-pixel normals (larger: smoother
    normals, fewer at edges)."""
    max_incidence_deg: float = 80.0
    """Points seen more obliquely than this (angle between the view ray and the surface
    normal) are dropped: their depth is unreliable."""

    def __post_init__(self) -> None:
        if self.normal_step_px < 1:
            raise ValueError("registration: normal_step_px must be >= 1")
        if not 0 < self.max_incidence_deg <= 90:
            raise ValueError("registration: max_incidence_deg must be in (0, 90]")


@dataclass(frozen=True)
class CameraPoints:
    """The valid pixels of one depth image as points."""

    points_world: FloatArray
    """(N, 3) metres, world frame."""
    normals_world: NDArray[np.float32]
    """(N, 3) unit normals facing the camera, world frame."""
    pixels: NDArray[np.int32]
    """(N, 2) integer pixel (x, y) each point came from."""
    colors: NDArray[np.uint8] | None
    """(N, 3) RGB of registered colour, or None."""


def pixel_rays(intrinsics: Intrinsics, pixels_xy: FloatArray) -> FloatArray:
    """(N, 3) rays (x/z, y/z, 1) through the given (N, 2) pixel centres, undistorted."""
    pts = np.asarray(pixels_xy, dtype=np.float64).reshape(-1, 2)
    if intrinsics.has_distortion:
        # Iterate to convergence: the default 5 iterations leave sub-pixel errors at the
        # image corners of strongly distorted lenses.
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
        norm = cv2.undistortPoints(pts.reshape(-1, 1, 2), intrinsics.matrix(),
                                   intrinsics.distortion_coeffs(),
                                   criteria=criteria).reshape(-1, 2)
    else:
        norm = np.column_stack([(pts[:, 0] - intrinsics.cx) / intrinsics.fx,
                                (pts[:, 1] - intrinsics.cy) / intrinsics.fy])
    return np.column_stack([norm, np.ones(len(norm))])


def ray_image(intrinsics: Intrinsics) -> NDArray[np.float32]:
    """(H, W, 3) float32 rays (x/z, y/z, 1) of every pixel centre."""
    if not intrinsics.has_distortion:
        rays = np.ones((intrinsics.height, intrinsics.width, 3), dtype=np.float32)
        rays[..., 0] = ((np.arange(intrinsics.width) - intrinsics.cx) / intrinsics.fx)[None, :]
        rays[..., 1] = ((np.arange(intrinsics.height) - intrinsics.cy) / intrinsics.fy)[:, None]
        return rays
    ys, xs = np.mgrid[0:intrinsics.height, 0:intrinsics.width]
    pix = np.column_stack([xs.ravel(), ys.ravel()]).astype(np.float64)
    return pixel_rays(intrinsics, pix).reshape(intrinsics.height, intrinsics.width,
                                               3).astype(np.float32)


def project(intrinsics: Intrinsics, points_cam: FloatArray) -> FloatArray:
    """(N, 2) pixel coordinates of (N, 3) camera-frame points (z > 0), with distortion."""
    pts = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
    if intrinsics.has_distortion:
        pix, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), intrinsics.matrix(),
                                   intrinsics.distortion_coeffs())
        return np.asarray(pix, dtype=np.float64).reshape(-1, 2)
    z = pts[:, 2]
    return np.column_stack([intrinsics.fx * pts[:, 0] / z + intrinsics.cx,
                            intrinsics.fy * pts[:, 1] / z + intrinsics.cy]).astype(np.float64)


def transform(a_from_b: FloatArray, points_b: FloatArray) -> FloatArray:
    """(N, 3) points moved by a 4x4 rigid transform."""
    return points_b @ a_from_b[:3, :3].T + a_from_b[:3, 3]


def invert_rigid(a_from_b: FloatArray) -> FloatArray:
    """The inverse of a 4x4 rigid transform (b_from_a)."""
    out = np.eye(4)
    out[:3, :3] = a_from_b[:3, :3].T
    out[:3, 3] = -a_from_b[:3, :3].T @ a_from_b[:3, 3]
    return out


def camera_points_image(depth_m: NDArray[np.float32], rays: NDArray[np.float32]
                        ) -> NDArray[np.float32]:
    """(H, W, 3) camera-frame points of a depth image (zeros where depth is 0)."""
    return rays * depth_m[..., None]


def normals_at(points_cam: NDArray[np.float32], valid: NDArray[np.bool_], step: int,
               ys: NDArray[np.intp], xs: NDArray[np.intp]
               ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """(N, 3) unit normals facing the camera at pixels (ys, xs), and where they are defined.

    Image-space differences span ``step`` pixels: central where both neighbours are valid,
    else one-sided, so pixels next to holes and silhouettes keep a normal; a normal needs a
    difference along both image axes. Only the given pixels are computed.
    """
    s = step
    padded = np.pad(points_cam, ((s, s), (s, s), (0, 0)))
    ok_pad = np.pad(valid, s)
    py, px = ys + s, xs + s
    centre = padded[py, px]
    diffs, oks = [], []
    for dy, dx in ((0, s), (s, 0)):
        ahead, behind = padded[py + dy, px + dx], padded[py - dy, px - dx]
        ok_ahead, ok_behind = ok_pad[py + dy, px + dx], ok_pad[py - dy, px - dx]
        diff = ahead - behind
        one_sided = ~(ok_ahead & ok_behind)
        diff[one_sided] = np.where(ok_ahead[one_sided, None], ahead[one_sided] - centre[one_sided],
                                   centre[one_sided] - behind[one_sided])
        diffs.append(diff)
        oks.append(ok_ahead | ok_behind)
    n = np.cross(diffs[0], diffs[1])
    length = np.linalg.norm(n, axis=1, keepdims=True)
    ok = valid[ys, xs] & oks[0] & oks[1] & (length[:, 0] > 0)
    n = np.divide(n, length, out=np.zeros_like(n), where=length > 0)
    # Orient towards the camera: the point's position vector points away from it.
    n[np.sum(n * centre, axis=1) > 0] *= -1
    n[~ok] = 0
    return n.astype(np.float32), ok


def normal_image(points_cam: NDArray[np.float32], valid: NDArray[np.bool_],
                 step: int) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """(H, W, 3) unit normals facing the camera (see :func:`normals_at`), and where defined."""
    ys, xs = np.nonzero(valid)
    normals = np.zeros(points_cam.shape, dtype=np.float32)
    ok = np.zeros(valid.shape, dtype=bool)
    n, has = normals_at(points_cam, valid, step, ys, xs)
    normals[ys, xs] = n
    ok[ys, xs] = has
    return normals, ok


def register_view(depth_m: NDArray[np.float32], intrinsics: Intrinsics,
                  world_from_depth: FloatArray, color_rgb: NDArray[np.uint8] | None,
                  config: RegistrationConfig, rays: NDArray[np.float32] | None = None
                  ) -> CameraPoints:
    """Back-project the valid pixels of one depth image into oriented world points.

    ``color_rgb`` must be registered to depth (same H, W) or None. ``rays`` may be given to
    reuse a precomputed :func:`ray_image`.
    """
    if depth_m.shape != (intrinsics.height, intrinsics.width):
        raise ValueError(f"depth_m: shape {depth_m.shape} does not match the intrinsics "
                         f"({intrinsics.height}, {intrinsics.width})")
    if color_rgb is not None and color_rgb.shape[:2] != depth_m.shape:
        raise ValueError("color_rgb: must be registered to depth (same height and width)")
    rays = ray_image(intrinsics) if rays is None else rays
    valid = depth_m > 0
    pts_cam = camera_points_image(depth_m, rays)
    ys, xs = np.nonzero(valid)
    normals_cam, has_normal = normals_at(pts_cam, valid, config.normal_step_px, ys, xs)
    view_dir = rays[ys, xs] / np.linalg.norm(rays[ys, xs], axis=1, keepdims=True)
    cos_inc = -np.sum(normals_cam * view_dir, axis=1)
    keep = has_normal & (cos_inc >= np.cos(np.radians(config.max_incidence_deg)))
    ys, xs, normals_cam = ys[keep], xs[keep], normals_cam[keep]
    rotation = world_from_depth[:3, :3]
    points_world = transform(world_from_depth, pts_cam[ys, xs].astype(np.float64))
    normals_world = (normals_cam.astype(np.float64) @ rotation.T).astype(np.float32)
    colors = None if color_rgb is None else color_rgb[ys, xs].astype(np.uint8)
    return CameraPoints(points_world=points_world, normals_world=normals_world,
                        pixels=np.column_stack([xs, ys]).astype(np.int32), colors=colors)
