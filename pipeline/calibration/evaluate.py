"""Comparing estimated camera poses with ground truth, across an arbitrary world frame."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from pipeline.calibration.transforms import fit_rigid, rotation_angle_deg

Matrix = NDArray[np.float64]


def align_to_truth(estimated: Mapping[str, Matrix], truth: Mapping[str, Matrix]) -> Matrix:
    """``truth_world_from_estimated_world``: Kabsch fit of the camera centres (3+ cameras), or
    the first camera's relative pose when there are fewer."""
    ids = [c for c in truth if c in estimated]
    if not ids:
        raise ValueError("pose comparison: no camera in common between estimate and truth")
    est = np.array([estimated[c][:3, 3] for c in ids])
    true = np.array([truth[c][:3, 3] for c in ids])
    if len(ids) >= 3 and np.linalg.svd(est - est.mean(axis=0), compute_uv=False)[1] > 1e-6:
        return fit_rigid(est, true)
    first = ids[0]
    return truth[first] @ np.linalg.inv(estimated[first])


def pose_errors(estimated: Mapping[str, Matrix], truth: Mapping[str, Matrix]) -> dict[str, Any]:
    """Per-camera rotation (degrees) and translation (mm) errors after alignment, with
    median and max over the cameras."""
    align = align_to_truth(estimated, truth)
    rotation, translation = {}, {}
    for camera_id, true_pose in truth.items():
        if camera_id not in estimated:
            continue
        moved = align @ estimated[camera_id]
        rotation[camera_id] = rotation_angle_deg(true_pose[:3, :3].T @ moved[:3, :3])
        translation[camera_id] = float(np.linalg.norm(true_pose[:3, 3] - moved[:3, 3]) * 1000)
    rot, trans = np.array(list(rotation.values())), np.array(list(translation.values()))
    return {"rotation_deg": rotation, "translation_mm": translation,
            "rotation_deg_median": float(np.median(rot)), "rotation_deg_max": float(rot.max()),
            "translation_mm_median": float(np.median(trans)),
            "translation_mm_max": float(trans.max())}
