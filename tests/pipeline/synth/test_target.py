"""Synthetic calibration captures: the target's geometry, and images that show it where the
true poses say (colour corners to a fraction of a pixel, depth on the plates)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from pipeline.calibration.detection import TargetDetector, target_geometry
from pipeline.calibration.transforms import invert, transform_points
from pipeline.synth.rig import RigConfig, rig_cameras
from pipeline.synth.target import (
    TargetSynthConfig,
    look_at_centre,
    make_target,
    synthesize_calibration,
    target_trajectory,
)


def test_cube_target_has_a_board_on_each_face_with_unique_markers() -> None:
    config = TargetSynthConfig(kind="cube")
    target, margins = make_target(config)
    assert len(target.boards) == 6
    ids = [set(range(b.first_marker_id, b.first_marker_id + 12)) for b in target.boards]
    assert len(set().union(*ids)) == 72
    side = 5 * config.square_length_m + 2 * margins[0][0]
    geometry = target_geometry(target)
    for index, board in enumerate(target.boards):
        points = geometry.points_target[geometry.board_of_point == index]
        inward = board.target_from_board[:3, 2]  # z goes into the printed face
        np.testing.assert_allclose(points @ inward, -side / 2, atol=1e-12)
        in_face = points - np.outer(points @ inward, inward)
        # Inner corners: one square in from the board's edge, the board centred on the face.
        np.testing.assert_allclose(np.abs(in_face).max(), 1.5 * config.square_length_m,
                                   atol=1e-12)
    assert not geometry.is_planar


def test_unknown_kind_is_refused() -> None:
    with pytest.raises(ValueError, match="'plane' or 'cube'"):
        TargetSynthConfig(kind="sphere")


@pytest.mark.parametrize("kind", ["plane", "cube"])
def test_rendered_views_show_the_target_where_the_truth_says(kind: str) -> None:
    config = TargetSynthConfig(kind=kind, frame_count=2, color_width=800, color_height=450,
                               color_fov_x_deg=80.0, depth_noise=False, seed=5)
    cameras = rig_cameras(RigConfig(camera_count=2, radius_m=1.5, width=320, height=288))
    meta, views, truth = synthesize_calibration(config, cameras=cameras)
    assert meta.target is not None and all(c.world_from_depth is None for c in meta.cameras)
    assert all(c.color_intrinsics is not None for c in meta.cameras)
    rng = np.random.default_rng(config.seed).spawn(2)[0]
    centre = look_at_centre(list(truth.values()))
    poses = target_trajectory(config, centre, [p[:3, 3] for p in truth.values()], rng)
    geometry = target_geometry(meta.target)
    detector = TargetDetector(geometry)
    checked = 0
    for view in views:
        camera = view.camera
        intrinsics = camera.color_intrinsics
        assert view.color_rgb is not None and intrinsics is not None
        assert camera.color_from_depth is not None
        assert view.color_rgb.shape == (450, 800, 3)
        ids, pixels = detector.detect(view.color_rgb, intrinsics)
        if len(ids) < 6:
            continue
        checked += 1
        color_from_target = camera.color_from_depth @ invert(truth[camera.id]) \
            @ poses[view.frame_index]
        projected, _ = cv2.projectPoints(
            geometry.points_target[ids], cv2.Rodrigues(color_from_target[:3, :3])[0],
            color_from_target[:3, 3], intrinsics.matrix(), intrinsics.distortion_coeffs())
        errors = np.linalg.norm(projected.reshape(-1, 2) - pixels, axis=1)
        assert np.sqrt(np.mean(errors**2)) < 0.1
        # The depth camera sees the plates at the corners' depth.
        depth_from_target = invert(truth[camera.id]) @ poses[view.frame_index]
        points = transform_points(depth_from_target, geometry.points_target[ids])
        d = camera.depth_intrinsics
        u = np.rint(points[:, 0] / points[:, 2] * d.fx + d.cx).astype(int)
        v = np.rint(points[:, 1] / points[:, 2] * d.fy + d.cy).astype(int)
        inside = (u >= 0) & (u < d.width) & (v >= 0) & (v < d.height)
        measured = view.depth_m[v[inside], u[inside]]
        assert np.all(np.abs(measured - points[inside, 2]) < 0.02)
    assert checked >= 2
