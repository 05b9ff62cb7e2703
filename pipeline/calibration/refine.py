"""The iterative scheme: refine poses from random frame subsets, reject outlier views by
their residual, until the error stops falling.

Each round (1) re-fits every camera pose against the current target poses using the views of
a random subset of frames, (2) re-fits every target pose against the cameras using all active
views, (3) drops views whose RMS stands far above the others'. Working on subsets keeps a few
bad frames from steering all cameras in one round; the final joint fit is bundle.py's.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from pipeline.calibration.bundle import Observations, bundle_adjust, residual_norms
from pipeline.calibration.config import CalibrationConfig
from pipeline.calibration.detection import TargetGeometry, ViewCorners

Matrix = NDArray[np.float64]


@dataclass(frozen=True)
class Problem:
    """The views of a calibration, indexed for the solvers."""

    camera_ids: tuple[str, ...]
    frames: tuple[int, ...]
    views: tuple[ViewCorners, ...]
    view_camera: NDArray[np.int64]
    """(V,) camera index of each view."""
    view_frame: NDArray[np.int64]
    """(V,) frame index (into ``frames``) of each view."""
    obs: Observations
    camera_matrices: Matrix
    """(C, 3, 3) colour camera matrices."""
    reference: int
    """Index of the camera that stays fixed (it carries the world frame)."""

    def subset(self, views: NDArray[np.bool_]) -> Observations:
        """The observations of the views flagged True."""
        keep = views[self.obs.view]
        return Observations(camera=self.obs.camera[keep], frame=self.obs.frame[keep],
                            view=self.obs.view[keep], point=self.obs.point[keep],
                            points_target=self.obs.points_target[keep],
                            pixels=self.obs.pixels[keep])


def build_problem(views: Sequence[ViewCorners], geometry: TargetGeometry,
                  camera_matrices: Mapping[str, Matrix], camera_ids: Sequence[str],
                  frames: Sequence[int], reference: str) -> Problem:
    """Index the views whose camera and frame are posed."""
    cam_index = {c: i for i, c in enumerate(camera_ids)}
    frame_index = {f: i for i, f in enumerate(frames)}
    kept = tuple(v for v in views if v.camera_id in cam_index and v.frame_index in frame_index)
    counts = [len(v.point_ids) for v in kept]
    view_camera = np.array([cam_index[v.camera_id] for v in kept], dtype=np.int64)
    view_frame = np.array([frame_index[v.frame_index] for v in kept], dtype=np.int64)
    view_of_obs = np.repeat(np.arange(len(kept)), counts)
    point_ids = np.concatenate([v.point_ids for v in kept])
    obs = Observations(camera=view_camera[view_of_obs], frame=view_frame[view_of_obs],
                       view=view_of_obs, point=point_ids,
                       points_target=geometry.points_target[point_ids],
                       pixels=np.concatenate([v.pixels for v in kept]))
    return Problem(camera_ids=tuple(camera_ids), frames=tuple(frames), views=kept,
                   view_camera=view_camera, view_frame=view_frame, obs=obs,
                   camera_matrices=np.stack([camera_matrices[c] for c in camera_ids]),
                   reference=cam_index[reference])


def view_rms(problem: Problem, color_from_world: Matrix, world_from_target: Matrix
             ) -> NDArray[np.float64]:
    """(V,) RMS reprojection error of every view, pixels."""
    norms = residual_norms(problem.obs, problem.camera_matrices, color_from_world,
                           world_from_target)
    sums = np.bincount(problem.obs.view, weights=norms**2, minlength=len(problem.views))
    counts = np.bincount(problem.obs.view, minlength=len(problem.views))
    return np.sqrt(sums / np.maximum(counts, 1))


def outlier_views(rms: NDArray[np.float64], active: NDArray[np.bool_],
                  view_camera: NDArray[np.int64], config: CalibrationConfig
                  ) -> NDArray[np.bool_]:
    """Active views whose RMS is far above the median (median + k * 1.4826 MAD).

    A camera always keeps its two best views, so rejection alone never removes a camera.
    """
    values = rms[active]
    median = float(np.median(values))
    sigma = 1.4826 * float(np.median(np.abs(values - median)))
    threshold = max(config.outlier_min_px, median + config.outlier_factor * sigma)
    out = active & (rms > threshold)
    for camera in np.unique(view_camera[out]):
        mine = np.flatnonzero(active & (view_camera == camera))
        protected = mine[np.argsort(rms[mine])[:2]]
        out[protected] = False
    return out


@dataclass(frozen=True)
class RefineResult:
    color_from_world: Matrix
    """(C, 4, 4) camera poses."""
    world_from_target: Matrix
    """(F, 4, 4) target poses."""
    active: NDArray[np.bool_]
    """(V,) views kept (not rejected as outliers)."""
    history_px: tuple[float, ...]
    """RMS reprojection error of the active views after each round."""


def _rms_of(rms: NDArray[np.float64], active: NDArray[np.bool_]) -> float:
    return float(np.sqrt(np.mean(rms[active] ** 2)))


def refine_poses(problem: Problem, color_from_world: Matrix, world_from_target: Matrix,
                 config: CalibrationConfig,
                 progress: Callable[[float], None] | None = None) -> RefineResult:
    """Rounds of subset refinement and outlier rejection until the error converges."""
    rng = np.random.default_rng(config.seed)
    n_frames = len(problem.frames)
    active = np.ones(len(problem.views), dtype=bool)
    no_cameras = np.zeros(len(problem.camera_ids), dtype=bool)
    history: list[float] = []
    subset_size = max(2, math.ceil(config.subset_fraction * n_frames))
    for round_index in range(config.max_iterations):
        chosen = rng.choice(n_frames, size=min(subset_size, n_frames), replace=False)
        in_subset = active & np.isin(problem.view_frame, chosen)
        free_cameras = np.isin(np.arange(len(problem.camera_ids)), problem.view_camera[in_subset])
        free_cameras[problem.reference] = False
        color_from_world, _ = bundle_adjust(
            problem.subset(in_subset), problem.camera_matrices, color_from_world,
            world_from_target, free_cameras, np.zeros(n_frames, dtype=bool),
            config.loss_scale_px, max_evaluations=30)
        free_targets = np.isin(np.arange(n_frames), problem.view_frame[active])
        _, world_from_target = bundle_adjust(
            problem.subset(active), problem.camera_matrices, color_from_world, world_from_target,
            no_cameras, free_targets, config.loss_scale_px, max_evaluations=30)
        rms = view_rms(problem, color_from_world, world_from_target)
        rejected = outlier_views(rms, active, problem.view_camera, config)
        active &= ~rejected
        history.append(_rms_of(rms, active))
        if progress is not None:
            progress((round_index + 1) / config.max_iterations)
        converged = (len(history) > 1
                     and history[-2] - history[-1] < config.convergence_tolerance * history[-2])
        if converged and not rejected.any():
            break
    return RefineResult(color_from_world, world_from_target, active, tuple(history))
