"""PnP recovers the pose of a board from its corners."""

from __future__ import annotations

import numpy as np
from hypothesis import assume, example, given, settings
from hypothesis import strategies as st

from pipeline.calibration.pnp import estimate_view_pose
from pipeline.calibration.transforms import from_rotvec, rotation_angle_deg
from tests.pipeline.calibration.corners import CAMERA_MATRIX, plane_geometry

GEOMETRY = plane_geometry()


def _project(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    cam = points @ pose[:3, :3].T + pose[:3, 3]
    pixels = cam @ CAMERA_MATRIX.T
    return pixels[:, :2] / pixels[:, 2:3]


@settings(max_examples=40, deadline=None)
@given(st.floats(-0.9, 0.9), st.floats(-0.9, 0.9), st.floats(-np.pi, np.pi),
       st.floats(-0.5, 0.3), st.floats(-0.4, 0.3), st.floats(0.8, 3.5))
@example(0.0, 0.0, -np.pi, 0.0, 0.3, 1.0)  # upside down: OpenCV's IPPE alone gets this wrong
@example(0.0, 0.0, np.pi, -0.5, -0.4, 3.5)
@example(0.0, 0.005, np.pi, -0.5, 0.0, 3.5)  # turned, slightly tilted: OpenCV's LM stops early
def test_pnp_recovers_a_known_pose(ax: float, ay: float, az: float, x: float, y: float,
                                   z: float) -> None:
    truth = from_rotvec(np.array([ax, ay, az]), np.array([x, y, z]))
    # A board seen within 10 degrees of edge-on shows no corners a detector would find.
    to_board = truth[:3, 3] / np.linalg.norm(truth[:3, 3])
    assume(abs(float(truth[:3, 2] @ to_board)) > np.sin(np.radians(10)))
    found = estimate_view_pose(GEOMETRY.points_target, _project(truth, GEOMETRY.points_target),
                               CAMERA_MATRIX)
    assert found is not None
    pose, rms = found
    assert rms < 1e-6
    assert rotation_angle_deg(pose[:3, :3].T @ truth[:3, :3]) < 1e-6
    np.testing.assert_allclose(pose[:3, 3], truth[:3, 3], atol=1e-6)


def test_pnp_on_non_planar_points() -> None:
    rng = np.random.default_rng(3)
    points = rng.uniform(-0.3, 0.3, (20, 3))
    truth = from_rotvec(np.array([0.2, -0.4, 0.1]), np.array([0.1, 0.0, 2.0]))
    pose, rms = estimate_view_pose(points, _project(truth, points), CAMERA_MATRIX) or (None, 0)
    assert pose is not None and rms < 1e-6
    np.testing.assert_allclose(pose, truth, atol=1e-6)


def test_pnp_refuses_collinear_and_too_few_points() -> None:
    truth = from_rotvec(np.zeros(3), np.array([0.0, 0.0, 2.0]))
    row = GEOMETRY.points_target[:5]  # the first row of corners: collinear
    assert estimate_view_pose(row, _project(truth, row), CAMERA_MATRIX) is None
    three = GEOMETRY.points_target[[0, 1, 7]]
    assert estimate_view_pose(three, _project(truth, three), CAMERA_MATRIX) is None
