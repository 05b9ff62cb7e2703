"""Rigid-transform helpers: 4x4 matrices named ``a_from_b`` (metres), rotation vectors,
averaging and rigid point-set fits.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

Matrix = NDArray[np.float64]


def rigid(rotation: Matrix, translation: Matrix) -> Matrix:
    """The 4x4 transform of a 3x3 rotation and a (3,) translation in metres."""
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = np.ravel(translation)
    return out


def invert(a_from_b: Matrix) -> Matrix:
    """``b_from_a`` of a rigid ``a_from_b`` (exact, no general matrix inverse)."""
    rotation = a_from_b[:3, :3]
    return rigid(rotation.T, -rotation.T @ a_from_b[:3, 3])


def from_rotvec(rotvec: Matrix, translation: Matrix) -> Matrix:
    """Rigid transform of a rotation vector (radians) and a translation (metres)."""
    return rigid(Rotation.from_rotvec(np.ravel(rotvec)).as_matrix(), translation)


def to_rotvec(a_from_b: Matrix) -> tuple[Matrix, Matrix]:
    """(rotation vector (3,) radians, translation (3,) metres) of a rigid transform."""
    return Rotation.from_matrix(a_from_b[:3, :3]).as_rotvec(), a_from_b[:3, 3].copy()


def transform_points(a_from_b: Matrix, points_b: Matrix) -> Matrix:
    """(N, 3) points in frame b moved into frame a."""
    return np.asarray(points_b, dtype=float) @ a_from_b[:3, :3].T + a_from_b[:3, 3]


def rotation_angle_deg(rotation: Matrix) -> float:
    """Angle of a 3x3 rotation in degrees (robust near 0 and 180)."""
    return float(np.degrees(np.linalg.norm(Rotation.from_matrix(rotation).as_rotvec())))


def project_to_rotation(matrix: Matrix) -> Matrix:
    """The rotation nearest (Frobenius) to a 3x3 matrix."""
    u, _, vt = np.linalg.svd(matrix)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def average_poses(poses: Sequence[Matrix], weights: Sequence[float] | None = None) -> Matrix:
    """Chordal mean of rotations and weighted mean of translations of rigid transforms."""
    if not poses:
        raise ValueError("average_poses: no poses to average")
    w = np.ones(len(poses)) if weights is None else np.asarray(weights, dtype=float)
    stack = np.stack(poses)
    rotation = project_to_rotation(np.einsum("n,nij->ij", w, stack[:, :3, :3]))
    translation = np.einsum("n,ni->i", w, stack[:, :3, 3]) / w.sum()
    return rigid(rotation, translation)


def robust_average_poses(poses: Sequence[Matrix], angle_deg: float = 2.0,
                         distance_m: float = 0.05) -> Matrix:
    """Average of the poses that agree with the medoid; disagreeing ones are outliers.

    The medoid is the pose with the smallest summed disagreement to the others, so one wrong
    pose (a flipped planar PnP, say) cannot drag the mean away.
    """
    if len(poses) <= 2:
        return average_poses(poses)
    stack = np.stack(poses)
    rel = np.einsum("nji,mjk->nmik", stack[:, :3, :3], stack[:, :3, :3])
    cos = np.clip((np.trace(rel, axis1=2, axis2=3) - 1.0) / 2.0, -1.0, 1.0)
    angles = np.degrees(np.arccos(cos))
    dists = np.linalg.norm(stack[:, None, :3, 3] - stack[None, :, :3, 3], axis=2)
    cost = angles / angle_deg + dists / distance_m
    medoid = int(np.argmin(cost.sum(axis=1)))
    keep = (angles[medoid] <= angle_deg) & (dists[medoid] <= distance_m)
    keep[medoid] = True
    return average_poses([p for p, k in zip(poses, keep, strict=True) if k])


def fit_rigid(points_src: Matrix, points_dst: Matrix) -> Matrix:
    """``dst_from_src`` minimising sum |dst - T src|^2 over rigid T (Kabsch, no scale).

    points_src, points_dst: (N, 3) matching points, N >= 3 and not collinear.
    """
    src = np.asarray(points_src, dtype=float)
    dst = np.asarray(points_dst, dtype=float)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError(f"fit_rigid needs two (N>=3, 3) point sets, got {src.shape}, {dst.shape}")
    mean_src, mean_dst = src.mean(axis=0), dst.mean(axis=0)
    cov = (dst - mean_dst).T @ (src - mean_src)
    rotation = project_to_rotation(cov)
    return rigid(rotation, mean_dst - rotation @ mean_src)
