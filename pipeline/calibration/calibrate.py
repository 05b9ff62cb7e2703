"""The calibration entry point: a ChArUco calibration capture in, ``world_from_depth`` out.

Steps: detect corners in every colour view, PnP per view, chain camera pairs
into a pose graph, iterate refinement with outlier rejection, bundle-adjust everything, then
optionally refine the depth cameras by ICP. The world is the reference camera's depth frame
turned to +Y up: x right, y up, z towards the back of that camera.
"""

from __future__ import annotations

import threading
from collections import defaultdict
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from pipeline.calibration.config import CalibrationConfig
from pipeline.calibration.depth_icp import Cloud, depth_cloud, refine_with_depth
from pipeline.calibration.detection import (
    TargetDetector,
    TargetGeometry,
    ViewCorners,
    target_geometry,
    undistort_pixels,
)
from pipeline.calibration.report import build_report
from pipeline.calibration.solve import solve_poses
from pipeline.calibration.transforms import invert
from pipeline.capture import CameraInfo, CaptureMeta, Intrinsics, View

Matrix = NDArray[np.float64]
Progress = Callable[[float], None]
WORLD_FROM_REFERENCE = np.diag([1.0, -1.0, -1.0, 1.0])
"""The reference depth camera's pose: OpenCV's y-down, z-forward turned to +Y up."""


class CaptureSource(Protocol):
    """What calibration reads of a capture (``pipeline.io.capture_io.CaptureReader``)."""

    meta: CaptureMeta

    def read_view(self, camera_id: str, frame_index: int, *, with_color: bool = True) -> View:
        ...


def color_model(camera: CameraInfo) -> tuple[Intrinsics, Matrix]:
    """(colour intrinsics, color_from_depth) of a camera; registered colour is the depth model."""
    if camera.color_intrinsics is None or camera.color_from_depth is None:
        return camera.depth_intrinsics, np.eye(4)
    return camera.color_intrinsics, np.asarray(camera.color_from_depth, dtype=float)


@dataclass
class _Detections:
    views: list[ViewCorners]
    detected: dict[str, int]
    with_color: dict[str, int]
    clouds: dict[str, dict[int, Cloud]]


def _detect_all(capture: CaptureSource, geometry: TargetGeometry, config: CalibrationConfig,
                progress: Progress | None) -> _Detections:
    meta = capture.meta
    local = threading.local()
    jobs = [(c, f) for f in meta.frame_indices for c in meta.cameras]

    def work(job: tuple[CameraInfo, int]
             ) -> tuple[str, int, ViewCorners | None, bool, Cloud | None]:
        camera, frame = job
        if not hasattr(local, "detector"):
            local.detector = TargetDetector(geometry)
        view = capture.read_view(camera.id, frame, with_color=True)
        cloud = None
        if config.icp:
            cloud = depth_cloud(view.depth_m, camera.depth_intrinsics, config.icp_voxel_size_m)
        if view.color_rgb is None:
            return camera.id, frame, None, False, cloud
        intrinsics = color_model(camera)[0]
        ids, pixels = local.detector.detect(view.color_rgb, intrinsics)
        if len(ids) < config.min_corners_per_view:
            return camera.id, frame, None, True, cloud
        corners = ViewCorners(camera.id, frame, ids, undistort_pixels(pixels, intrinsics))
        return camera.id, frame, corners, True, cloud

    found = _Detections([], defaultdict(int), defaultdict(int), defaultdict(dict))
    with ThreadPoolExecutor(max_workers=config.workers) as pool:
        results: Iterator[Any] = pool.map(work, jobs)
        for done, (camera_id, frame, corners, had_color, cloud) in enumerate(results, start=1):
            found.with_color[camera_id] += int(had_color)
            if corners is not None:
                found.views.append(corners)
                found.detected[camera_id] += 1
            if cloud is not None:
                found.clouds[camera_id][frame] = cloud
            if progress is not None:
                progress(done / len(jobs))
    return found


def _check_detections(meta: CaptureMeta, found: _Detections) -> None:
    colourless = [c for c in meta.camera_ids if found.with_color[c] == 0]
    if colourless:
        raise ValueError(f"calibration: camera(s) {', '.join(colourless)} have no colour images; "
                         "ChArUco calibration needs colour")
    if not found.views:
        boards = "; ".join(f"{b.dictionary} {b.squares_x}x{b.squares_y}"
                           for b in meta.target.boards) if meta.target else "none"
        raise ValueError("calibration: no ChArUco corners of the target were found in any colour "
                         f"image (target boards: {boards}); is the target in view, and does "
                         "capture.json describe the printed board?")


def _scaled(progress: Progress | None, start: float, end: float) -> Progress | None:
    if progress is None:
        return None
    return lambda fraction: progress(start + (end - start) * min(max(fraction, 0.0), 1.0))


def calibrate(capture: CaptureSource, config: CalibrationConfig | None = None,
              progress: Progress | None = None) -> tuple[dict[str, Matrix], dict[str, Any]]:
    """``world_from_depth`` (4x4, metres) per camera id, and the quality report.

    Raises ValueError naming the problem: no target described or found, unknown dictionary,
    cameras without colour, cameras that never saw the target or share no frame with the rest.
    """
    config = config or CalibrationConfig()
    meta = capture.meta
    geometry = target_geometry(meta.target)
    reference = config.reference_camera or meta.camera_ids[0]
    if reference not in meta.camera_ids:
        raise ValueError(f"reference_camera: capture has no camera {reference!r}")
    found = _detect_all(capture, geometry, config, _scaled(progress, 0.0, 0.6))
    _check_detections(meta, found)
    matrices = {c.id: color_model(c)[0].matrix() for c in meta.cameras}
    solution = solve_poses(found.views, geometry, matrices, meta.camera_ids, reference, config,
                           _scaled(progress, 0.6, 0.9))
    if progress is not None:
        progress(0.95)
    report = build_report(solution.problem, solution.active, solution.color_from_world,
                          solution.world_from_target, geometry.points_target, found.detected,
                          list(solution.history_px), config)
    world_from_depth = _depth_poses(meta, solution.color_from_world, reference)
    if config.icp:
        world_from_depth, icp_report = refine_with_depth(found.clouds, world_from_depth,
                                                         reference, config)
        report["icp"] = icp_report["corrections"]
        report["warnings"] += icp_report["warnings"]
    report["reference_camera"] = reference
    report["world_frame"] = (f"depth frame of {reference} turned to +Y up (x right, y up, "
                             "z backwards)")
    if progress is not None:
        progress(1.0)
    return world_from_depth, report


def _depth_poses(meta: CaptureMeta, color_from_world: Matrix, reference: str
                 ) -> dict[str, Matrix]:
    """world_from_depth per camera, the world re-based on the reference depth camera."""
    color_from_depth = {c.id: color_model(c)[1] for c in meta.cameras}
    ref_index = meta.camera_ids.index(reference)
    # Solver world -> new world: the reference depth camera becomes WORLD_FROM_REFERENCE.
    rebase = WORLD_FROM_REFERENCE @ invert(color_from_depth[reference]) \
        @ color_from_world[ref_index]
    return {camera_id: rebase @ invert(color_from_world[i]) @ color_from_depth[camera_id]
            for i, camera_id in enumerate(meta.camera_ids)}
