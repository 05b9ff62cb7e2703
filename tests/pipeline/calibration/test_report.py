"""The quality report: exact data give zero errors; errors in the data show up where they are;
thin evidence and bad cameras get warnings."""

from __future__ import annotations

import dataclasses

import numpy as np

from pipeline.calibration.config import CalibrationConfig
from pipeline.calibration.report import build_report, triangulate
from pipeline.calibration.solve import solve_poses
from pipeline.calibration.transforms import invert, transform_points
from tests.pipeline.calibration.corners import (
    CAMERA_MATRIX,
    observe,
    plane_geometry,
    ring_cameras,
    target_poses,
)

GEOMETRY = plane_geometry()
IDS = ["a", "b", "c"]


def _solved(views: list, config: CalibrationConfig) -> dict:
    solution = solve_poses(views, GEOMETRY, {c: CAMERA_MATRIX for c in IDS}, IDS, "a", config)
    return build_report(solution.problem, solution.active, solution.color_from_world,
                        solution.world_from_target, GEOMETRY.points_target,
                        {c: 5 for c in IDS}, list(solution.history_px), config)


def test_exact_corners_give_zero_errors() -> None:
    rng = np.random.default_rng(4)
    cameras, targets = ring_cameras(3, rng), target_poses(5, rng)
    report = _solved(observe(GEOMETRY, cameras, targets, IDS), CalibrationConfig())
    assert max(report["reprojection_rms_px"].values()) < 1e-6
    assert report["triangulation_error_mm"]["max"] < 1e-6
    assert report["triangulation_error_mm"]["points"] == 5 * len(GEOMETRY.points_target)
    assert report["views_used"] == {"a": 5, "b": 5, "c": 5}
    assert report["warnings"] == [] and report["rejected_views"] == []


def test_triangulation_recovers_world_points() -> None:
    rng = np.random.default_rng(5)
    cameras, targets = ring_cameras(3, rng), target_poses(2, rng)
    solution = solve_poses(observe(GEOMETRY, cameras, targets, IDS), GEOMETRY,
                           {c: CAMERA_MATRIX for c in IDS}, IDS, "a", CalibrationConfig())
    frames, points, world = triangulate(solution.problem.obs, solution.problem.camera_matrices,
                                        solution.color_from_world)
    for frame, point, position in zip(frames, points, world, strict=True):
        expected = transform_points(solution.world_from_target[frame],
                                    GEOMETRY.points_target[point][None])[0]
        np.testing.assert_allclose(position, expected, atol=1e-9)
    # The solver's world is camera a's frame: world points are where camera a saw them.
    first = transform_points(invert(cameras[0]) @ targets[0], GEOMETRY.points_target)
    np.testing.assert_allclose(world[frames == 0], first[points[frames == 0]], atol=1e-6)


def test_noisy_camera_and_thin_evidence_are_warned_about() -> None:
    rng = np.random.default_rng(6)
    cameras, targets = ring_cameras(3, rng), target_poses(5, rng)
    views = []
    for view in observe(GEOMETRY, cameras, targets, IDS):
        if view.camera_id == "c" and view.frame_index >= 3:
            continue  # c saw the target three times only
        sigma = 1.5 if view.camera_id == "b" else 0.05
        views.append(dataclasses.replace(view, pixels=view.pixels
                                         + rng.normal(0, sigma, view.pixels.shape)))
    report = _solved(views, CalibrationConfig(outlier_min_px=10.0))
    assert report["views_used"]["c"] == 3
    assert report["reprojection_rms_px"]["b"] > 1.0 > report["reprojection_rms_px"]["a"]
    warnings = " ".join(report["warnings"])
    assert "camera c used only 3 view(s)" in warnings
    assert "camera b has a reprojection RMS" in warnings and "camera a" not in warnings
    assert report["triangulation_error_mm"]["median"] > 0.1
