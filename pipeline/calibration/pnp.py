"""Per-view target poses by PnP on undistorted ChArUco corners."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from pipeline.calibration.transforms import from_rotvec

_PLANAR_TOLERANCE_M = 1e-6
# OpenCV's default stops after 20 iterations or a step below FLT_EPSILON; near a 180-degree
# turn with a slight tilt that leaves up to 1e-5 degrees and 3e-6 px on exact corners.
_LM_CRITERIA = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-15)


def _is_planar(points: NDArray[np.float64]) -> bool:
    centred = points - points.mean(axis=0)
    return bool(np.linalg.svd(centred, compute_uv=False)[2] < _PLANAR_TOLERANCE_M)


def _spread_enough(pixels: NDArray[np.float64]) -> bool:
    # Collinear corners (one row of a board) leave the pose undetermined.
    centred = pixels - pixels.mean(axis=0)
    singular = np.linalg.svd(centred, compute_uv=False)
    return bool(singular[1] > 1e-3 * max(singular[0], 1e-12) and singular[1] > 1.0)


def reprojection_rms(points_cam: NDArray[np.float64], pixels: NDArray[np.float64],
                     camera_matrix: NDArray[np.float64]) -> float:
    """RMS pixel distance between observed pixels (N, 2) and projected camera points (N, 3)."""
    projected = points_cam @ camera_matrix.T
    projected = projected[:, :2] / projected[:, 2:3]
    return float(np.sqrt(np.mean(np.sum((projected - pixels) ** 2, axis=1))))


def _candidates(points: NDArray[np.float64], image: NDArray[np.float64],
                camera_matrix: NDArray[np.float64]) -> list[NDArray[np.float64]]:
    """Starting poses: both IPPE solutions for a planar set, and SQPnP's.

    OpenCV's IPPE returns a wrong rotation for a board turned exactly 180 degrees in its
    plane (its rotation-vector conversion breaks down there); SQPnP gets that case right.
    """
    methods = [cv2.SOLVEPNP_IPPE, cv2.SOLVEPNP_SQPNP] if _is_planar(points) else \
        [cv2.SOLVEPNP_SQPNP]
    starts = []
    for method in methods:
        try:
            count, rvecs, tvecs, _ = cv2.solvePnPGeneric(points, image, camera_matrix, None,
                                                         flags=method)
        except cv2.error:
            continue
        starts += [from_rotvec(np.asarray(rvecs[i], np.float64).ravel(),
                               np.asarray(tvecs[i], np.float64).ravel()) for i in range(count)]
    return starts


def _polish(points: NDArray[np.float64], image: NDArray[np.float64],
            camera_matrix: NDArray[np.float64], start: NDArray[np.float64]
            ) -> NDArray[np.float64]:
    """Levenberg-Marquardt on the rotation relative to ``start``.

    OpenCV refines a rotation vector, which is singular at 180 degrees (a board seen upside
    down): started there it can wander off. Rotating the points by the start first leaves a
    correction near zero, where the rotation vector is well-behaved.
    """
    turned = np.ascontiguousarray(points @ start[:3, :3].T)
    rvec, tvec = cv2.solvePnPRefineLM(turned, image, camera_matrix, None, np.zeros((3, 1)),
                                      start[:3, 3].reshape(3, 1).copy(), criteria=_LM_CRITERIA)
    delta = from_rotvec(np.asarray(rvec, np.float64).ravel(), np.asarray(tvec, np.float64).ravel())
    if not np.all(np.isfinite(delta)):
        return start
    pose = delta.copy()
    pose[:3, :3] = delta[:3, :3] @ start[:3, :3]
    return pose


def estimate_view_pose(points_target: NDArray[np.float64], pixels: NDArray[np.float64],
                       camera_matrix: NDArray[np.float64]
                       ) -> tuple[NDArray[np.float64], float] | None:
    """``camera_from_target`` (4x4) and its RMS reprojection error in pixels, or None.

    points_target: (N, 3) corner positions in the target frame, metres. pixels: (N, 2)
    undistorted pixels. Planar sets try both IPPE solutions and SQPnP's, others SQPnP; each
    is polished by Levenberg-Marquardt and the best kept. None when the points cannot fix a pose
    (fewer than 4, collinear) or the target would lie behind the camera.
    """
    points = np.ascontiguousarray(points_target, dtype=np.float64).reshape(-1, 3)
    image = np.ascontiguousarray(pixels, dtype=np.float64).reshape(-1, 2)
    if len(points) < 4 or not _spread_enough(image):
        return None
    best: tuple[NDArray[np.float64], float] | None = None
    for start in _candidates(points, image, camera_matrix):
        if not np.all(np.isfinite(start)):
            continue  # OpenCV gives NaN on some degenerate sets
        pose = _polish(points, image, camera_matrix, start)
        points_cam = points @ pose[:3, :3].T + pose[:3, 3]
        if np.any(points_cam[:, 2] <= 0):
            continue
        rms = reprojection_rms(points_cam, image, camera_matrix)
        if best is None or rms < best[1]:
            best = (pose, rms)
    return best
