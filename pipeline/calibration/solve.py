"""From ChArUco corners to camera poses: PnP per view, pose graph, iterative refinement with
outlier rejection, and the final global bundle adjustment."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from pipeline.calibration.bundle import bundle_adjust
from pipeline.calibration.config import CalibrationConfig
from pipeline.calibration.detection import TargetGeometry, ViewCorners
from pipeline.calibration.pnp import estimate_view_pose
from pipeline.calibration.pose_graph import initial_poses
from pipeline.calibration.refine import (
    Problem,
    build_problem,
    outlier_views,
    refine_poses,
    view_rms,
)
from pipeline.calibration.transforms import invert

Matrix = NDArray[np.float64]
Progress = Callable[[float], None]


@dataclass(frozen=True)
class Solution:
    """Poses in the solver's world (the reference camera's colour frame)."""

    problem: Problem
    color_from_world: Matrix
    """(C, 4, 4) colour camera poses, in ``problem.camera_ids`` order."""
    world_from_target: Matrix
    """(F, 4, 4) target poses, in ``problem.frames`` order."""
    active: NDArray[np.bool_]
    """(V,) views kept after outlier rejection."""
    history_px: tuple[float, ...]
    """RMS reprojection error after each refinement round."""


def view_poses(views: Sequence[ViewCorners], geometry: TargetGeometry,
               camera_matrices: Mapping[str, Matrix]
               ) -> tuple[list[ViewCorners], dict[tuple[str, int], Matrix]]:
    """The views PnP could pose, and their ``color_from_target``."""
    kept, poses = [], {}
    for view in views:
        result = estimate_view_pose(geometry.points_target[view.point_ids], view.pixels,
                                    camera_matrices[view.camera_id])
        if result is not None:
            kept.append(view)
            poses[(view.camera_id, view.frame_index)] = result[0]
    return kept, poses


def _final_bundle(problem: Problem, color_from_world: Matrix, targets: Matrix,
                  active: NDArray[np.bool_], config: CalibrationConfig
                  ) -> tuple[Matrix, Matrix, NDArray[np.bool_]]:
    """Global bundle adjustment; once more if it exposes further outlier views."""
    free_cameras = np.ones(len(problem.camera_ids), dtype=bool)
    free_cameras[problem.reference] = False
    for _ in range(2):
        free_targets = np.isin(np.arange(len(problem.frames)), problem.view_frame[active])
        color_from_world, targets = bundle_adjust(
            problem.subset(active), problem.camera_matrices, color_from_world, targets,
            free_cameras, free_targets, config.loss_scale_px)
        rejected = outlier_views(view_rms(problem, color_from_world, targets), active,
                                 problem.view_camera, config)
        if not rejected.any():
            break
        active = active & ~rejected
    return color_from_world, targets, active


def solve_poses(views: Sequence[ViewCorners], geometry: TargetGeometry,
                camera_matrices: Mapping[str, Matrix], camera_ids: Sequence[str],
                reference: str, config: CalibrationConfig,
                progress: Progress | None = None) -> Solution:
    """Camera and target poses from undistorted corners of every view.

    Raises ValueError naming the cameras that saw no usable view or that no shared frame
    joins to the reference camera.
    """
    posed, poses = view_poses(views, geometry, camera_matrices)
    world_from_color, world_from_target = initial_poses(poses, camera_ids, reference)
    frames = tuple(world_from_target)
    problem = build_problem(posed, geometry, camera_matrices, camera_ids, frames, reference)
    refined = refine_poses(problem, np.stack([invert(world_from_color[c]) for c in camera_ids]),
                           np.stack([world_from_target[f] for f in frames]), config, progress)
    color_from_world, targets, active = _final_bundle(
        problem, refined.color_from_world, refined.world_from_target, refined.active, config)
    return Solution(problem, color_from_world, targets, active, refined.history_px)
