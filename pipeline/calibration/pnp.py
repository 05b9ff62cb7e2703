"""Per-view target poses by PnP on undistorted ChArUco corners."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from pipeline.calibration.transforms import from_rotvec

_PLANAR_TOLERANCE_M = 1e-6


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


def estimate_view_pose(points_target: NDArray[np.float64], pixels: NDArray[np.float64],
                       camera_matrix: NDArray[np.float64]
                       ) -> tuple[NDArray[np.float64], float] | None:
    """``camera_from_target`` (4x4) and its RMS reprojection error in pixels, or None.

    points_target: (N, 3) corner positions in the target frame, metres. pixels: (N, 2)
    undistorted pixels. Planar sets use IPPE (both of its solutions are tried), others SQPnP;
    the best is polished by Levenberg-Marquardt. None when the points cannot fix a pose
    (fewer than 4, collinear) or the target would lie behind the camera.
    """
    points = np.ascontiguousarray(points_target, dtype=np.float64).reshape(-1, 3)
    image = np.ascontiguousarray(pixels, dtype=np.float64).reshape(-1, 2)
    if len(points) < 4 or not _spread_enough(image):
        return None
    method = cv2.SOLVEPNP_IPPE if _is_planar(points) else cv2.SOLVEPNP_SQPNP
    try:
        count, rvecs, tvecs, _ = cv2.solvePnPGeneric(points, image, camera_matrix, None,
                                                     flags=method)
    except cv2.error:
        return None
    best: tuple[NDArray[np.float64], float] | None = None
    for i in range(count):
        rvec, tvec = cv2.solvePnPRefineLM(points, image, camera_matrix, None,
                                          rvecs[i].copy(), tvecs[i].copy())
        rotvec = np.asarray(rvec, np.float64).ravel()
        translation = np.asarray(tvec, np.float64).ravel()
        if not (np.all(np.isfinite(rotvec)) and np.all(np.isfinite(translation))):
            continue  # OpenCV gives NaN on some degenerate sets
        pose = from_rotvec(rotvec, translation)
        points_cam = points @ pose[:3, :3].T + pose[:3, 3]
        if np.any(points_cam[:, 2] <= 0):
            continue
        rms = reprojection_rms(points_cam, image, camera_matrix)
        if best is None or rms < best[1]:
            best = (pose, rms)
    return best
