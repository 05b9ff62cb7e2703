"""The overlap equations of the alignment and their robust least-squares solve.

Where camera j's point p_j falls on camera i's surface (point p_i, normal n), a correction
D_k(p) = w_k x (p - c_k) + t_k + beta_k r_k(p) of each camera k (small rotation w about its
centre c, translation t, range change beta along the unit ray r) must close the gap s:

    n . (D_j(p_j) - D_i(p_i)) = -s

Every overlap sample is one linear equation in the 7 unknowns of two cameras. A robust
(Huber-weighted) least squares solve with weak zero-mean priors gives the corrections; a
camera held fixed keeps a zero correction. `pipeline.reconstruct.align` decides which
corrections are kept.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np
from numpy.typing import NDArray

from pipeline.reconstruct.registration import camera_points_image, normal_image, project, ray_image

if TYPE_CHECKING:
    from pipeline.reconstruct.align import AlignConfig, DepthView

FloatArray = NDArray[np.float64]
UNKNOWNS = 7
"""Rotation (3), translation (3), range (1) per camera."""
_FIXED_PRECISION = 1e12
"""Prior precision that holds an unknown at zero."""


@dataclass(frozen=True)
class SampledCamera:
    """A camera's sampled pixels in its own frame (computed once)."""

    points: FloatArray
    """(N, 3) sampled points, camera frame, metres."""
    normals: FloatArray
    unit_rays: FloatArray
    image_points: NDArray[np.float32]
    image_normals: NDArray[np.float32]
    image_ok: NDArray[np.bool_]
    image_unit_rays: NDArray[np.float32]
    view: DepthView


def sample_camera(view: DepthView, step: int, margin: int) -> SampledCamera:
    """Every ``step``-th pixel of the view well inside a surface, with its normal."""
    rays = ray_image(view.intrinsics)
    unit = rays / np.linalg.norm(rays, axis=2, keepdims=True)
    pts = camera_points_image(view.depth_m, rays)
    valid = view.depth_m > 0
    normals, ok = normal_image(pts, valid, 2)
    # Only pixels well inside a surface: filtering and mixed returns bias the rim.
    interior = cv2.erode(valid.astype(np.uint8), np.ones((2 * margin + 1, 2 * margin + 1),
                                                          np.uint8)) > 0 if margin else valid
    ok = ok & interior
    sub = ok[::step, ::step]
    return SampledCamera(points=pts[::step, ::step][sub].astype(np.float64),
                         normals=normals[::step, ::step][sub].astype(np.float64),
                         unit_rays=unit[::step, ::step][sub].astype(np.float64),
                         image_points=pts, image_normals=normals, image_ok=ok,
                         image_unit_rays=unit, view=view)


@dataclass(frozen=True)
class Matches:
    """Overlap samples of camera j on camera i: one equation row block per camera."""

    row_i: FloatArray
    """(M, 7) coefficients of camera i's unknowns."""
    row_j: FloatArray
    """(M, 7) coefficients of camera j's unknowns."""
    rhs: FloatArray
    """(M,) right-hand sides (minus the current gap), metres."""
    half: NDArray[np.bool_]
    """(M,) which half of the overlaps each sample belongs to (alternate cubes of the world),
    for checks on held-out samples."""

    def select(self, keep: NDArray[np.bool_]) -> Matches:
        return Matches(self.row_i[keep], self.row_j[keep], self.rhs[keep], self.half[keep])


def _to_world(pose: FloatArray, points: FloatArray, directions: FloatArray
              ) -> tuple[FloatArray, FloatArray]:
    rot = pose[:3, :3]
    return points @ rot.T + pose[:3, 3], directions @ rot.T


def pair_matches(cams: list[SampledCamera], poses: FloatArray, offsets: FloatArray, i: int,
                 j: int, config: AlignConfig) -> Matches:
    """Camera j's samples that land on camera i's surface, as equations (see module doc)."""
    cj, ci = cams[j], cams[i]
    pts_j = cj.points - offsets[j] * cj.unit_rays
    p_j, n_j = _to_world(poses[j], pts_j, cj.normals)
    r_j = cj.unit_rays @ poses[j][:3, :3].T
    i_from_world = np.linalg.inv(poses[i])
    in_i = p_j @ i_from_world[:3, :3].T + i_from_world[:3, 3]
    front = in_i[:, 2] > 1e-6
    pix = np.full((len(in_i), 2), -1.0)
    pix[front] = project(ci.view.intrinsics, in_i[front])
    x, y = np.rint(pix[:, 0]).astype(np.int64), np.rint(pix[:, 1]).astype(np.int64)
    h, w = ci.image_ok.shape
    inside = front & (x >= 0) & (x < w) & (y >= 0) & (y < h)
    x, y = np.where(inside, x, 0), np.where(inside, y, 0)
    unit_i = ci.image_unit_rays[y, x].astype(np.float64)
    pts_i = ci.image_points[y, x].astype(np.float64) - offsets[i] * unit_i
    p_i, n_i = _to_world(poses[i], pts_i, ci.image_normals[y, x].astype(np.float64))
    r_i = unit_i @ poses[i][:3, :3].T
    cos_lim = np.cos(np.radians(config.max_incidence_deg))
    agree = np.sum(n_i * n_j, axis=1) >= np.cos(np.radians(config.max_normal_angle_deg))
    use = (inside & ci.image_ok[y, x] & agree
           & (-np.sum(n_i * r_i, axis=1) >= cos_lim) & (-np.sum(n_j * r_j, axis=1) >= cos_lim)
           & (np.abs(in_i[:, 2] - pts_i[:, 2]) < config.gate_m))
    p_i, p_j, r_i, r_j = p_i[use], p_j[use], r_i[use], r_j[use]
    n = n_i[use] + n_j[use]
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    gap = np.sum((p_j - p_i) * n, axis=1)
    # Halves by place, not by pixel: the samples of one spot by either camera of the pair then
    # share a half, so no pixel's noise is in both.
    blocks = np.floor(p_j / config.heldout_block_m).astype(np.int64)

    def row(p: FloatArray, centre: FloatArray, r: FloatArray) -> FloatArray:
        return np.column_stack([np.cross(p - centre, n), n, np.sum(r * n, axis=1)])

    return Matches(row_i=-row(p_i, poses[i][:3, 3], r_i), row_j=row(p_j, poses[j][:3, 3], r_j),
                   rhs=-gap, half=(blocks.sum(axis=1) % 2).astype(bool))


def _prior(camera_count: int, config: AlignConfig, fixed: frozenset[int], gauge: bool
           ) -> FloatArray:
    """Prior precision of the unknowns: zero-mean priors on each (huge where a kind is
    switched off or a camera held fixed) and, with ``gauge``, a stiff one on the free
    cameras' mean rotation and translation, which the overlaps cannot see (moving every
    camera alike moves the whole scene)."""
    rot = 1.0 / np.radians(config.rotation_prior_deg) ** 2 if config.poses else _FIXED_PRECISION
    trans = 1.0 / config.translation_prior_m**2 if config.poses else _FIXED_PRECISION
    rng = 1.0 / config.offset_prior_m**2 if config.offsets else _FIXED_PRECISION
    per_camera = np.tile([rot] * 3 + [trans] * 3 + [rng], (camera_count, 1))
    for k in fixed:
        per_camera[k] = _FIXED_PRECISION
    precision = np.diag(per_camera.ravel())
    free = [k for k in range(camera_count) if k not in fixed]
    if gauge and free and config.poses:
        weights = np.zeros((1, camera_count))
        weights[0, free] = 1.0 / len(free)
        mean_of = np.kron(weights, np.eye(UNKNOWNS)[:6])
        precision += mean_of.T @ (1e6 * np.diag([rot] * 3 + [trans] * 3)) @ mean_of
    return precision


def is_anchored(matches: dict[tuple[int, int], Matches], fixed: frozenset[int]) -> bool:
    """Whether a fixed camera shares overlaps with a free one (it then holds the rig's
    position, and no gauge prior is needed)."""
    return any((i in fixed) != (j in fixed) for i, j in matches)


def solve(matches: dict[tuple[int, int], Matches], camera_count: int, config: AlignConfig,
          fixed: frozenset[int] = frozenset()) -> FloatArray:
    """(C, 7) corrections minimising the Huber loss of the equations plus the priors; the
    cameras in ``fixed`` keep zero."""
    x = np.zeros((camera_count, UNKNOWNS))
    prior = _prior(camera_count, config, fixed, gauge=not is_anchored(matches, fixed))
    for _ in range(config.iterations):
        normal = prior.copy()
        rhs = np.zeros(camera_count * UNKNOWNS)
        for (i, j), m in matches.items():
            residual = m.row_i @ x[i] + m.row_j @ x[j] - m.rhs
            scale = np.abs(residual) / config.huber_m
            weight = np.where(scale <= 1.0, 1.0, 1.0 / np.maximum(scale, 1e-12))
            weight /= config.huber_m**2
            for a, row_a in ((i, m.row_i), (j, m.row_j)):
                block_a = slice(a * UNKNOWNS, (a + 1) * UNKNOWNS)
                rhs[block_a] += (row_a * (weight * m.rhs)[:, None]).sum(axis=0)
                for b, row_b in ((i, m.row_i), (j, m.row_j)):
                    block_b = slice(b * UNKNOWNS, (b + 1) * UNKNOWNS)
                    normal[block_a, block_b] += (row_a * weight[:, None]).T @ row_b
        x = np.asarray(np.linalg.solve(normal, rhs), dtype=np.float64).reshape(
            camera_count, UNKNOWNS)
    x[sorted(fixed)] = 0.0
    return x


def apply_correction(poses: FloatArray, offsets: FloatArray, x: FloatArray
                     ) -> tuple[FloatArray, FloatArray]:
    """Poses turned about their centres and moved; offsets less the range changes."""
    new_poses = poses.copy()
    for k, (omega, shift) in enumerate(zip(x[:, :3], x[:, 3:6], strict=True)):
        rot, _ = cv2.Rodrigues(omega.reshape(3, 1))
        centre = poses[k][:3, 3]
        motion = np.eye(4)
        motion[:3, :3] = rot
        motion[:3, 3] = centre - rot @ centre + shift
        new_poses[k] = motion @ poses[k]
    return new_poses, offsets - x[:, 6]


def shifts_m(cam: SampledCamera, pose: FloatArray, x: FloatArray) -> FloatArray:
    """(N,) how far the correction ``x`` (7,) moves each of the camera's samples, metres."""
    rot = pose[:3, :3]
    moved = (np.cross(x[:3], cam.points @ rot.T) + x[3:6]
             + x[6] * (cam.unit_rays @ rot.T))
    return np.asarray(np.linalg.norm(moved, axis=1), dtype=np.float64)
