"""Alignment of the cameras on their overlaps: per-camera range offsets and pose touch-ups.

Time-of-flight cameras measure range with a small constant offset per unit (a few mm for
the Azure Kinect), which no extrinsic calibration removes, and a calibrated rig keeps pose
residuals of a fraction of a degree and a few millimetres. Both leave the cameras' surfaces
apart where they overlap, and whichever camera a region is taken from shows its own error.

Where camera j's point p_j falls on camera i's surface (point p_i, normal n), a correction
D_k(p) = w_k x (p - c_k) + t_k + beta_k r_k(p) of each camera k (small rotation w about its
centre c, translation t, range change beta along the unit ray r) must close the gap s:

    n . (D_j(p_j) - D_i(p_i)) = -s

Every overlap sample is one linear equation in the 7 unknowns of two cameras. A robust
(Huber-weighted) least squares solve with weak zero-mean priors (which also fix the free
rigid motion of the whole rig) gives the corrections; matches are then redrawn with the
corrected cameras and the solve repeated, as in multi-view ICP.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from pipeline.capture import Intrinsics
from pipeline.reconstruct.registration import camera_points_image, normal_image, project, ray_image

FloatArray = NDArray[np.float64]
_UNKNOWNS = 7  # rotation (3), translation (3), range (1) per camera


@dataclass(frozen=True)
class AlignConfig:
    """How cameras are aligned on their overlaps."""

    offsets: bool = True
    """Estimate per-camera range offsets."""
    poses: bool = True
    """Also touch up the camera poses (small rotations and translations)."""
    sample_step_px: int = 4
    """Every this many pixels (in x and y) of each camera are matched against the others."""
    edge_margin_px: int = 3
    """Pixels this close to a hole or silhouette are not matched (their depth is biased by
    mixed returns and one-sided filtering)."""
    gate_m: float = 0.02
    """Matches farther apart than this along the view ray are different surfaces."""
    max_normal_angle_deg: float = 30.0
    """Matches whose two normals differ by more than this are dropped."""
    max_incidence_deg: float = 65.0
    """Matches seen more obliquely than this by either camera are dropped."""
    huber_m: float = 0.002
    """Residuals beyond this weigh less (Huber loss), metres."""
    offset_prior_m: float = 0.01
    """Standard deviation of the zero-mean prior on each range offset, metres."""
    rotation_prior_deg: float = 0.25
    """Standard deviation of the zero-mean prior on each pose rotation, degrees (a rig
    calibration's residuals; it keeps directions the overlaps barely see, such as a turn
    about a round subject's axis, where they are)."""
    translation_prior_m: float = 0.003
    """Standard deviation of the zero-mean prior on each pose translation, metres."""
    rounds: int = 1
    """Match-and-solve rounds (matches are redrawn with the corrected cameras); one is as
    good as more for errors well within the gate (a few tenths of a degree, a few mm)."""
    iterations: int = 6
    """Reweighted least-squares iterations per round."""
    min_matches: int = 50
    """A camera pair with fewer matches than this contributes nothing."""

    def __post_init__(self) -> None:
        if self.sample_step_px < 1 or self.rounds < 1 or self.iterations < 1:
            raise ValueError("align: sample_step_px, rounds and iterations must be >= 1")
        if not (self.gate_m > 0 and self.huber_m > 0 and self.offset_prior_m > 0
                and self.rotation_prior_deg > 0 and self.translation_prior_m > 0):
            raise ValueError("align: gate_m, huber_m and the priors must be > 0")


@dataclass(frozen=True)
class DepthView:
    """One filtered depth image with its camera model and pose."""

    depth_m: NDArray[np.float32]
    """(H, W) metres, 0 = invalid."""
    intrinsics: Intrinsics
    world_from_depth: FloatArray
    """4x4 camera pose, metres."""


@dataclass(frozen=True)
class Corrections:
    """What the alignment found."""

    offsets_m: FloatArray
    """(C,) range offset of each camera, metres: measured range = true range + offset."""
    world_from_depth: FloatArray
    """(C, 4, 4) corrected camera poses."""


@dataclass(frozen=True)
class _Camera:
    """A camera's sampled pixels in its own frame (computed once)."""

    points: FloatArray
    normals: FloatArray
    unit_rays: FloatArray
    image_points: NDArray[np.float32]
    image_normals: NDArray[np.float32]
    image_ok: NDArray[np.bool_]
    image_unit_rays: NDArray[np.float32]
    view: DepthView


def _prepare(view: DepthView, step: int, margin: int) -> _Camera:
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
    return _Camera(points=pts[::step, ::step][sub].astype(np.float64),
                   normals=normals[::step, ::step][sub].astype(np.float64),
                   unit_rays=unit[::step, ::step][sub].astype(np.float64),
                   image_points=pts, image_normals=normals, image_ok=ok,
                   image_unit_rays=unit, view=view)


@dataclass(frozen=True)
class _Matches:
    """Overlap samples of camera j on camera i: one equation row block per camera."""

    row_i: FloatArray
    """(M, 7) coefficients of camera i's unknowns."""
    row_j: FloatArray
    """(M, 7) coefficients of camera j's unknowns."""
    rhs: FloatArray
    """(M,) right-hand sides (minus the current gap), metres."""


def _to_world(pose: FloatArray, points: FloatArray, directions: FloatArray
              ) -> tuple[FloatArray, FloatArray]:
    rot = pose[:3, :3]
    return points @ rot.T + pose[:3, 3], directions @ rot.T


def pair_matches(cams: list[_Camera], poses: FloatArray, offsets: FloatArray, i: int, j: int,
                 config: AlignConfig) -> _Matches:
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

    def row(p: FloatArray, centre: FloatArray, r: FloatArray) -> FloatArray:
        return np.column_stack([np.cross(p - centre, n), n, np.sum(r * n, axis=1)])

    return _Matches(row_i=-row(p_i, poses[i][:3, 3], r_i), row_j=row(p_j, poses[j][:3, 3], r_j),
                    rhs=-gap)


def _prior(camera_count: int, config: AlignConfig) -> FloatArray:
    """Prior precision of the unknowns: zero-mean priors on each (huge where a kind is
    switched off), and a stiff one on the rig's mean rotation and translation, which the
    overlaps cannot see (moving every camera alike moves the whole scene)."""
    rot = 1.0 / np.radians(config.rotation_prior_deg) ** 2 if config.poses else 1e12
    trans = 1.0 / config.translation_prior_m**2 if config.poses else 1e12
    rng = 1.0 / config.offset_prior_m**2 if config.offsets else 1e12
    precision = np.diag(np.tile([rot] * 3 + [trans] * 3 + [rng], camera_count))
    mean_of = np.kron(np.ones((1, camera_count)) / camera_count, np.eye(_UNKNOWNS)[:6])
    stiff = 1e6 * np.diag([rot] * 3 + [trans] * 3)
    return precision + mean_of.T @ stiff @ mean_of


def solve(matches: dict[tuple[int, int], _Matches], camera_count: int,
          config: AlignConfig) -> FloatArray:
    """(C, 7) corrections minimising the Huber loss of the equations plus the priors."""
    x = np.zeros((camera_count, _UNKNOWNS))
    prior = _prior(camera_count, config)
    for _ in range(config.iterations):
        normal = prior.copy()
        rhs = np.zeros(camera_count * _UNKNOWNS)
        for (i, j), m in matches.items():
            residual = m.row_i @ x[i] + m.row_j @ x[j] - m.rhs
            scale = np.abs(residual) / config.huber_m
            weight = np.where(scale <= 1.0, 1.0, 1.0 / np.maximum(scale, 1e-12))
            weight /= config.huber_m**2
            for a, row_a in ((i, m.row_i), (j, m.row_j)):
                block_a = slice(a * _UNKNOWNS, (a + 1) * _UNKNOWNS)
                rhs[block_a] += (row_a * (weight * m.rhs)[:, None]).sum(axis=0)
                for b, row_b in ((i, m.row_i), (j, m.row_j)):
                    block_b = slice(b * _UNKNOWNS, (b + 1) * _UNKNOWNS)
                    normal[block_a, block_b] += (row_a * weight[:, None]).T @ row_b
        x = np.asarray(np.linalg.solve(normal, rhs), dtype=np.float64).reshape(
            camera_count, _UNKNOWNS)
    return x


def _apply(poses: FloatArray, offsets: FloatArray, x: FloatArray
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


def estimate_corrections(views: list[DepthView], config: AlignConfig) -> Corrections:
    """Range offsets and corrected poses of the cameras from their overlaps."""
    camera_count = len(views)
    poses = np.array([np.asarray(v.world_from_depth, dtype=np.float64) for v in views])
    offsets = np.zeros(camera_count)
    if camera_count < 2 or not (config.offsets or config.poses):
        return Corrections(offsets, poses)
    cams = [_prepare(v, config.sample_step_px, config.edge_margin_px) for v in views]
    for _ in range(config.rounds):
        matches = {}
        for i in range(camera_count):
            for j in range(camera_count):
                if i != j:
                    m = pair_matches(cams, poses, offsets, i, j, config)
                    if len(m.rhs) >= config.min_matches:
                        matches[(i, j)] = m
        if not matches:
            break
        poses, offsets = _apply(poses, offsets, solve(matches, camera_count, config))
    return Corrections(offsets, poses)


def apply_offsets(depth_m: NDArray[np.float32], rays: NDArray[np.float32],
                  offset_m: float) -> NDArray[np.float32]:
    """Depth with the camera's range offset removed (invalid pixels stay 0).

    rays: (H, W, 3) from :func:`pipeline.reconstruct.registration.ray_image`; the offset is
    along each ray, so z changes by offset / |ray|.
    """
    corrected = depth_m - np.float32(offset_m) / np.linalg.norm(rays, axis=2)
    return np.where(depth_m > 0, np.maximum(corrected, np.float32(1e-6)),
                    np.float32(0.0)).astype(np.float32)
