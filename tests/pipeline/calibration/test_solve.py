"""Poses from corners: noise-free observations give the exact rig back; the bundle
adjustment's analytic Jacobian matches finite differences; bad graphs fail by name."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.calibration.bundle import Observations, _jacobian, _Parameters, project
from pipeline.calibration.config import CalibrationConfig
from pipeline.calibration.pose_graph import initial_poses
from pipeline.calibration.solve import solve_poses
from pipeline.calibration.transforms import from_rotvec, invert, rotation_angle_deg
from tests.pipeline.calibration.corners import (
    CAMERA_MATRIX,
    observe,
    plane_geometry,
    ring_cameras,
    target_poses,
)

GEOMETRY = plane_geometry()


@settings(max_examples=12, deadline=None)
@given(st.integers(2, 5), st.integers(3, 6), st.integers(0, 2**31))
def test_noise_free_corners_give_the_rig_back(cameras: int, frames: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    world_from_camera = ring_cameras(cameras, rng)
    ids = [f"c{i}" for i in range(cameras)]
    views = observe(GEOMETRY, world_from_camera, target_poses(frames, rng), ids)
    solution = solve_poses(views, GEOMETRY, {c: CAMERA_MATRIX for c in ids}, ids, ids[0],
                           CalibrationConfig())
    assert solution.active.all()
    # The solver's world is the reference camera's frame: compare relative poses.
    for i in range(1, cameras):
        truth = invert(world_from_camera[0]) @ world_from_camera[i]
        found = invert(solution.color_from_world[i])
        assert rotation_angle_deg(truth[:3, :3].T @ found[:3, :3]) < 1e-6
        np.testing.assert_allclose(found[:3, 3], truth[:3, 3], atol=1e-6)


def test_a_bad_view_is_rejected_and_the_rig_still_recovered() -> None:
    rng = np.random.default_rng(7)
    world_from_camera = ring_cameras(4, rng)
    ids = ["a", "b", "c", "d"]
    views = observe(GEOMETRY, world_from_camera, target_poses(6, rng), ids)
    noisy = []
    for view in views:
        pixels = view.pixels + rng.normal(0, 0.05, view.pixels.shape)
        if (view.camera_id, view.frame_index) == ("b", 2):
            pixels = pixels + rng.normal(0, 6.0, pixels.shape)  # a smeared, wrong detection
        noisy.append(dataclasses.replace(view, pixels=pixels))
    solution = solve_poses(noisy, GEOMETRY, {c: CAMERA_MATRIX for c in ids}, ids, "a",
                           CalibrationConfig())
    rejected = [(solution.problem.views[i].camera_id, solution.problem.views[i].frame_index)
                for i in np.flatnonzero(~solution.active)]
    assert rejected == [("b", 2)]
    truth = invert(world_from_camera[0]) @ world_from_camera[1]
    np.testing.assert_allclose(invert(solution.color_from_world[1])[:3, 3], truth[:3, 3],
                               atol=2e-3)


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 2**31))
def test_bundle_jacobian_matches_finite_differences(seed: int) -> None:
    rng = np.random.default_rng(seed)
    cameras = np.stack([invert(p) for p in ring_cameras(3, rng)])
    targets = np.stack(target_poses(4, rng))
    n = 40
    obs = Observations(camera=rng.integers(0, 3, n), frame=rng.integers(0, 4, n),
                       view=np.zeros(n, np.int64), point=np.arange(n),
                       points_target=GEOMETRY.points_target[rng.integers(0, 20, n)],
                       pixels=np.zeros((n, 2)))
    matrices = np.stack([CAMERA_MATRIX] * 3)
    params = _Parameters(cameras, targets, np.array([False, True, True]), np.ones(4, bool))
    x = rng.normal(0, 0.05, params.size)

    def pixels(x: np.ndarray) -> np.ndarray:
        return project(obs, matrices, *params.poses(x)).ravel()

    analytic = _jacobian(obs, matrices, params, x).toarray()
    numeric = np.zeros_like(analytic)
    for i in range(params.size):
        step = np.zeros(params.size)
        step[i] = 1e-6
        numeric[:, i] = (pixels(x + step) - pixels(x - step)) / 2e-6
    np.testing.assert_allclose(analytic, numeric, atol=1e-4 * np.abs(analytic).max())


def _relative(rng: np.random.Generator) -> np.ndarray:
    return from_rotvec(rng.normal(0, 0.3, 3), rng.normal(0, 0.5, 3))


def test_disconnected_graph_names_the_cameras() -> None:
    rng = np.random.default_rng(0)
    poses = {("a", 0): _relative(rng), ("b", 0): _relative(rng),
             ("c", 1): _relative(rng), ("d", 1): _relative(rng)}
    with pytest.raises(ValueError, match=r"disconnected: camera\(s\) c, d share no target"):
        initial_poses(poses, ["a", "b", "c", "d"], "a")


def test_camera_that_never_saw_the_target_is_named() -> None:
    rng = np.random.default_rng(0)
    poses = {("a", 0): _relative(rng), ("b", 0): _relative(rng)}
    with pytest.raises(ValueError, match=r"camera\(s\) c saw no usable view"):
        initial_poses(poses, ["a", "b", "c"], "a")


def test_target_seen_by_one_camera_at_a_time_is_refused() -> None:
    rng = np.random.default_rng(0)
    poses = {("a", 0): _relative(rng), ("b", 1): _relative(rng)}
    with pytest.raises(ValueError, match="no frame shows the target to two cameras"):
        initial_poses(poses, ["a", "b"], "a")
