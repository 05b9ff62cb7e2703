"""Sparse bundle adjustment of camera poses and target poses over ChArUco corners.

Unknowns: 6 per free camera (``color_from_world``) and 6 per free target pose
(``world_from_target``), each a rotation-vector increment of the starting rotation plus a
translation. Every corner residual depends on one camera and one target pose only, so the
analytic Jacobian handed to scipy's ``least_squares`` (trust region, LSMR) is sparse: 24
non-zeros per corner.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.sparse import csr_matrix
from scipy.spatial.transform import Rotation

Matrix = NDArray[np.float64]


@dataclass(frozen=True)
class Observations:
    """Corner observations flattened over views (index arrays into cameras and frames)."""

    camera: NDArray[np.int64]
    """(N,) camera index of each corner observation."""
    frame: NDArray[np.int64]
    """(N,) target-pose (frame) index of each corner observation."""
    view: NDArray[np.int64]
    """(N,) view index of each corner observation."""
    point: NDArray[np.int64]
    """(N,) target point id of each corner observation."""
    points_target: Matrix
    """(N, 3) corner position in the target frame, metres."""
    pixels: Matrix
    """(N, 2) observed undistorted pixels."""

    def __len__(self) -> int:
        return len(self.camera)


def project(obs: Observations, camera_matrices: Matrix, color_from_world: Matrix,
            world_from_target: Matrix) -> Matrix:
    """(N, 2) pixels where the poses put every observed corner."""
    target_pose = world_from_target[obs.frame]
    camera_pose = color_from_world[obs.camera]
    points_world = np.einsum("nij,nj->ni", target_pose[:, :3, :3], obs.points_target) \
        + target_pose[:, :3, 3]
    points_cam = np.einsum("nij,nj->ni", camera_pose[:, :3, :3], points_world) \
        + camera_pose[:, :3, 3]
    homogeneous = np.einsum("nij,nj->ni", camera_matrices[obs.camera], points_cam)
    return homogeneous[:, :2] / homogeneous[:, 2:3]


def residual_norms(obs: Observations, camera_matrices: Matrix, color_from_world: Matrix,
                   world_from_target: Matrix) -> NDArray[np.float64]:
    """(N,) pixel distance between observed and projected corners."""
    predicted = project(obs, camera_matrices, color_from_world, world_from_target)
    return np.linalg.norm(predicted - obs.pixels, axis=1)


def _skew(v: Matrix) -> Matrix:
    """(N, 3, 3) cross-product matrices of (N, 3) vectors."""
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2], out[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    out[..., 1, 0], out[..., 2, 0], out[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    return out


def _left_jacobian(rotvec: Matrix) -> Matrix:
    """(N, 3, 3) left Jacobians of SO(3): d exp(w + d) = exp(J d) exp(w) to first order."""
    theta = np.linalg.norm(rotvec, axis=-1)[..., None, None]
    small = theta < 1e-5
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 0.5 - theta**2 / 24, (1 - np.cos(safe)) / safe**2)
    b = np.where(small, 1 / 6 - theta**2 / 120, (safe - np.sin(safe)) / safe**3)
    skew = _skew(rotvec)
    return np.eye(3) + a * skew + b * (skew @ skew)


class _Parameters:
    """Pose unknowns: a rotation-vector increment (on the side of the pose's own origin,
    left for ``color_from_world``, right for ``world_from_target``, keeping rotation and
    translation nearly decoupled) and a translation increment per free pose."""

    def __init__(self, cameras: Matrix, targets: Matrix, free_cameras: NDArray[np.bool_],
                 free_targets: NDArray[np.bool_]) -> None:
        self.cameras, self.targets = cameras, targets
        self.free_cameras, self.free_targets = free_cameras, free_targets
        self.n_cam = int(free_cameras.sum())
        self.cam_column = np.full(len(free_cameras), -1, dtype=np.int64)
        self.cam_column[free_cameras] = np.arange(self.n_cam) * 6
        self.target_column = np.full(len(free_targets), -1, dtype=np.int64)
        self.target_column[free_targets] = self.n_cam * 6 + np.arange(int(free_targets.sum())) * 6
        self.size = 6 * (self.n_cam + int(free_targets.sum()))

    def increments(self, x: Matrix) -> tuple[Matrix, Matrix]:
        """(C, 6) and (F, 6) increments, zero for the fixed poses."""
        cam = np.zeros((len(self.free_cameras), 6))
        target = np.zeros((len(self.free_targets), 6))
        cam[self.free_cameras] = x[: self.n_cam * 6].reshape(-1, 6)
        target[self.free_targets] = x[self.n_cam * 6:].reshape(-1, 6)
        return cam, target

    def poses(self, x: Matrix) -> tuple[Matrix, Matrix]:
        """(color_from_world (C, 4, 4), world_from_target (F, 4, 4)) at parameters x."""
        cam, target = self.increments(x)
        cameras, targets = self.cameras.copy(), self.targets.copy()
        turn_cam = Rotation.from_rotvec(cam[:, :3]).as_matrix()
        turn_target = Rotation.from_rotvec(target[:, :3]).as_matrix()
        cameras[:, :3, :3] = turn_cam @ self.cameras[:, :3, :3]
        cameras[:, :3, 3] += cam[:, 3:]
        targets[:, :3, :3] = self.targets[:, :3, :3] @ turn_target
        targets[:, :3, 3] += target[:, 3:]
        return cameras, targets


def _jacobian(obs: Observations, camera_matrices: Matrix, params: _Parameters,
              x: Matrix) -> csr_matrix:
    """Sparse (2N, P) Jacobian of the pixel residuals, analytic."""
    cam_inc, target_inc = params.increments(x)
    cameras, targets = params.poses(x)
    rc, rt0 = cameras[obs.camera, :3, :3], params.targets[obs.frame, :3, :3]
    turned = np.einsum("nij,nj->ni", Rotation.from_rotvec(target_inc[obs.frame, :3]).as_matrix(),
                       obs.points_target)
    points_world = np.einsum("nij,nj->ni", rt0, turned) + targets[obs.frame, :3, 3]
    rotated = np.einsum("nij,nj->ni", rc, points_world)
    p = rotated + cameras[obs.camera, :3, 3]
    k = camera_matrices[obs.camera]
    z = p[:, 2]
    d_proj = np.zeros((len(obs), 2, 3))
    d_proj[:, 0, 0], d_proj[:, 0, 2] = k[:, 0, 0] / z, -k[:, 0, 0] * p[:, 0] / z**2
    d_proj[:, 1, 1], d_proj[:, 1, 2] = k[:, 1, 1] / z, -k[:, 1, 1] * p[:, 1] / z**2
    d_proj[:, 0, 1] = k[:, 0, 1] / z  # skew, zero for ordinary cameras
    d_proj[:, 0, 2] -= k[:, 0, 1] * p[:, 1] / z**2
    cam_rot = -_skew(rotated) @ _left_jacobian(cam_inc[obs.camera, :3])
    target_rot = rc @ rt0 @ (-_skew(turned) @ _left_jacobian(target_inc[obs.frame, :3]))
    blocks = [(params.cam_column[obs.camera], np.concatenate([d_proj @ cam_rot, d_proj], axis=2)),
              (params.target_column[obs.frame],
               np.concatenate([d_proj @ target_rot, d_proj @ rc], axis=2))]
    rows, cols, vals = [], [], []
    for first_column, block in blocks:
        used = first_column >= 0
        n_used = int(used.sum())
        rows.append(np.repeat(np.flatnonzero(used)[:, None] * 2 + np.arange(2), 6, axis=1).ravel())
        cols.append((first_column[used][:, None, None] + np.arange(6)[None, None, :]
                     + np.zeros((1, 2, 1), dtype=np.int64)).reshape(n_used * 12))
        vals.append(block[used].reshape(-1))
    return csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(2 * len(obs), params.size))


def bundle_adjust(obs: Observations, camera_matrices: Matrix, color_from_world: Matrix,
                  world_from_target: Matrix, free_cameras: NDArray[np.bool_],
                  free_targets: NDArray[np.bool_], loss_scale_px: float = 1.0,
                  max_evaluations: int = 100) -> tuple[Matrix, Matrix]:
    """Refined (color_from_world (C, 4, 4), world_from_target (F, 4, 4)).

    Only the poses flagged free move; fixing one camera removes the world frame's freedom.
    Huber loss with scale ``loss_scale_px`` keeps a few bad corners from pulling the fit.
    The Jacobian is analytic and sparse (each corner touches one camera and one target pose).
    """
    params = _Parameters(color_from_world, world_from_target, free_cameras, free_targets)
    if len(obs) == 0 or params.size == 0:
        return color_from_world.copy(), world_from_target.copy()

    def residuals(x: Matrix) -> Matrix:
        cameras, targets = params.poses(x)
        return (project(obs, camera_matrices, cameras, targets) - obs.pixels).ravel()

    result = least_squares(residuals, np.zeros(params.size), method="trf",
                           jac=lambda x: _jacobian(obs, camera_matrices, params, x),
                           loss="huber", f_scale=loss_scale_px, x_scale="jac",
                           xtol=1e-10, ftol=1e-10, gtol=1e-10, max_nfev=max_evaluations)
    return params.poses(result.x)
