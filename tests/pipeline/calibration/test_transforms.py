"""Rigid-transform helpers: inverses, rotation vectors, averages and Kabsch fits."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from pipeline.calibration.transforms import (
    average_poses,
    fit_rigid,
    from_rotvec,
    invert,
    robust_average_poses,
    rotation_angle_deg,
    to_rotvec,
    transform_points,
)

vectors = arrays(np.float64, 3, elements=st.floats(-3.0, 3.0))
rotvecs = arrays(np.float64, 3, elements=st.floats(-1.5, 1.5))


@given(rotvecs, vectors)
def test_invert_undoes_the_transform(rotvec: np.ndarray, translation: np.ndarray) -> None:
    pose = from_rotvec(rotvec, translation)
    np.testing.assert_allclose(invert(pose) @ pose, np.eye(4), atol=1e-12)
    np.testing.assert_allclose(pose @ invert(pose), np.eye(4), atol=1e-12)


@given(rotvecs, vectors)
def test_rotvec_round_trip(rotvec: np.ndarray, translation: np.ndarray) -> None:
    back_r, back_t = to_rotvec(from_rotvec(rotvec, translation))
    np.testing.assert_allclose(from_rotvec(back_r, back_t), from_rotvec(rotvec, translation),
                               atol=1e-12)
    assert abs(rotation_angle_deg(from_rotvec(rotvec, translation)[:3, :3])
               - np.degrees(np.linalg.norm(rotvec))) < 1e-9


@given(rotvecs, vectors, st.integers(0, 2**31))
def test_fit_rigid_recovers_a_known_motion(rotvec: np.ndarray, translation: np.ndarray,
                                           seed: int) -> None:
    points = np.random.default_rng(seed).uniform(-1, 1, (12, 3))
    truth = from_rotvec(rotvec, translation)
    np.testing.assert_allclose(fit_rigid(points, transform_points(truth, points)), truth,
                               atol=1e-9)


@given(rotvecs, vectors)
def test_averages_of_equal_poses_are_that_pose(rotvec: np.ndarray, translation: np.ndarray
                                               ) -> None:
    pose = from_rotvec(rotvec, translation)
    np.testing.assert_allclose(average_poses([pose, pose, pose]), pose, atol=1e-12)
    np.testing.assert_allclose(robust_average_poses([pose] * 4), pose, atol=1e-12)


@settings(max_examples=30)
@given(rotvecs, vectors, st.integers(0, 2**31))
def test_robust_average_ignores_a_flipped_pose(rotvec: np.ndarray, translation: np.ndarray,
                                               seed: int) -> None:
    rng = np.random.default_rng(seed)
    pose = from_rotvec(rotvec, translation)
    near = [pose @ from_rotvec(rng.normal(0, 1e-3, 3), rng.normal(0, 1e-3, 3))
            for _ in range(4)]
    flipped = pose @ from_rotvec(np.array([np.pi * 0.8, 0.0, 0.0]), np.array([0.0, 0.0, 0.3]))
    mean = robust_average_poses(near + [flipped])
    assert rotation_angle_deg(mean[:3, :3].T @ pose[:3, :3]) < 0.5
    assert np.linalg.norm(mean[:3, 3] - pose[:3, 3]) < 0.01


def test_fit_rigid_refuses_too_few_points() -> None:
    try:
        fit_rigid(np.zeros((2, 3)), np.zeros((2, 3)))
    except ValueError as exc:
        assert "N>=3" in str(exc)
    else:
        raise AssertionError("expected ValueError")
