"""The quality report of a calibration: reprojection errors, triangulation errors against the
known target geometry, views used per camera, and warnings a person should read."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from pipeline.calibration.bundle import Observations, residual_norms
from pipeline.calibration.config import CalibrationConfig
from pipeline.calibration.refine import Problem, view_rms
from pipeline.calibration.transforms import fit_rigid, invert, transform_points

Matrix = NDArray[np.float64]


def triangulate(obs: Observations, camera_matrices: Matrix, color_from_world: Matrix
                ) -> tuple[NDArray[np.int64], NDArray[np.int64], Matrix]:
    """Corners seen by two or more cameras in one frame, placed where their rays meet best.

    Returns (frame index (P,), point id (P,), points_world (P, 3) metres): for each corner the
    point with the least summed squared distance to the observing rays.
    """
    if len(obs) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3))
    keys = obs.frame * (int(obs.point.max()) + 1) + obs.point
    unique, group, counts = np.unique(keys, return_inverse=True, return_counts=True)
    world_from_color = np.stack([invert(p) for p in color_from_world])
    centres = world_from_color[obs.camera, :3, 3]
    rays_cam = np.einsum("nij,nj->ni", np.linalg.inv(camera_matrices)[obs.camera],
                         np.column_stack([obs.pixels, np.ones(len(obs))]))
    rays = np.einsum("nij,nj->ni", world_from_color[obs.camera, :3, :3], rays_cam)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    projector = np.eye(3) - rays[:, :, None] * rays[:, None, :]
    lhs = np.zeros((len(unique), 3, 3))
    rhs = np.zeros((len(unique), 3))
    np.add.at(lhs, group, projector)
    np.add.at(rhs, group, np.einsum("nij,nj->ni", projector, centres))
    keep = counts >= 2
    points = np.linalg.solve(lhs[keep], rhs[keep][..., None])[..., 0]
    first = np.zeros(len(unique), dtype=np.int64)
    first[group[::-1]] = np.arange(len(obs))[::-1]
    return obs.frame[first[keep]], obs.point[first[keep]], points


def triangulation_errors_m(obs: Observations, camera_matrices: Matrix, color_from_world: Matrix,
                           points_target: Matrix) -> NDArray[np.float64]:
    """Distances, metres, between triangulated corners and the known target fitted to them.

    Per frame, the target's own geometry is fitted rigidly (Kabsch) to the corners the cameras
    triangulated, so these errors measure the rig alone, not the estimated target poses.
    """
    frames, point_ids, points_world = triangulate(obs, camera_matrices, color_from_world)
    errors = []
    for frame in np.unique(frames):
        mine = frames == frame
        if mine.sum() < 4:
            continue
        known = points_target[point_ids[mine]]
        if np.linalg.svd(known - known.mean(axis=0), compute_uv=False)[1] < 1e-6:
            continue  # collinear corners fix no rigid fit
        fit = fit_rigid(known, points_world[mine])
        errors.append(np.linalg.norm(transform_points(fit, known) - points_world[mine], axis=1))
    return np.concatenate(errors) if errors else np.zeros(0)


def _stats_mm(values_m: NDArray[np.float64]) -> dict[str, float | int]:
    if len(values_m) == 0:
        return {"points": 0}
    mm = values_m * 1000.0
    return {"mean": float(mm.mean()), "median": float(np.median(mm)),
            "rms": float(np.sqrt(np.mean(mm**2))), "max": float(mm.max()), "points": len(mm)}


def build_report(problem: Problem, active: NDArray[np.bool_], color_from_world: Matrix,
                 world_from_target: Matrix, points_target: Matrix,
                 views_detected: Mapping[str, int], history_px: list[float],
                 config: CalibrationConfig) -> dict[str, Any]:
    """The report dictionary written beside the poses in rig.json."""
    obs = problem.subset(active)
    norms = residual_norms(obs, problem.camera_matrices, color_from_world, world_from_target)
    per_camera_rms, views_used, corners_used, warnings = {}, {}, {}, []
    for index, camera_id in enumerate(problem.camera_ids):
        mine = obs.camera == index
        views_used[camera_id] = int(np.sum(active & (problem.view_camera == index)))
        corners_used[camera_id] = int(mine.sum())
        per_camera_rms[camera_id] = float(np.sqrt(np.mean(norms[mine] ** 2))) if mine.any() \
            else float("nan")
        if views_used[camera_id] < config.min_views_warning:
            warnings.append(f"camera {camera_id} used only {views_used[camera_id]} view(s) of the "
                            f"target (fewer than {config.min_views_warning}): its pose rests on "
                            "little evidence; capture more frames where it sees the target")
        if per_camera_rms[camera_id] > config.max_rms_warning_px:
            warnings.append(f"camera {camera_id} has a reprojection RMS of "
                            f"{per_camera_rms[camera_id]:.2f} px (above "
                            f"{config.max_rms_warning_px} px): check its intrinsics")
    rms_views = view_rms(problem, color_from_world, world_from_target)
    rejected = [{"camera": problem.views[i].camera_id, "frame": problem.views[i].frame_index,
                 "rms_px": float(rms_views[i])} for i in np.flatnonzero(~active)]
    return {
        "reprojection_rms_px": per_camera_rms,
        "reprojection_rms_px_all": float(np.sqrt(np.mean(norms**2))) if len(norms) else None,
        "triangulation_error_mm": _stats_mm(triangulation_errors_m(
            obs, problem.camera_matrices, color_from_world, points_target)),
        "views_detected": dict(views_detected),
        "views_used": views_used,
        "corners_used": corners_used,
        "frames_used": int(len(np.unique(problem.view_frame[active]))),
        "refinement_rms_px": [float(h) for h in history_px],
        "rejected_views": rejected,
        "warnings": warnings,
    }
