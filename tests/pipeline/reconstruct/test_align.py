from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.reconstruct.align import AlignConfig, DepthView, apply_offsets, estimate_corrections
from pipeline.reconstruct.registration import RegistrationConfig, ray_image, register_view
from tests.pipeline.sphere_scene import CENTRE, RADIUS, ring_cameras, sphere_depth

# A big ball with two small ones stuck to it: no symmetry hides a camera's rotation.
BALLS = ((CENTRE, RADIUS), (CENTRE + np.array([0.3, 0.2, 0.1]), 0.12),
         (CENTRE + np.array([-0.2, -0.25, 0.2]), 0.15))


def _distance_to_balls(points: np.ndarray) -> np.ndarray:
    return np.min([np.linalg.norm(points - c, axis=1) - r for c, r in BALLS], axis=0)


def _views(biases: list[float], noise_m: float = 0.0, pose_deg: float = 0.0,
           pose_m: float = 0.0, seed: int = 1) -> list[DepthView]:
    """Depth rendered from the true poses; the views carry poses with errors of zero mean
    (the rig's mean pose is what overlaps cannot correct: it moves the whole scene)."""
    rng = np.random.default_rng(seed)
    cams = ring_cameras(len(biases), 320, 288)
    turns = rng.normal(size=(len(cams), 3))
    shifts = rng.normal(size=(len(cams), 3))
    turns -= turns.mean(axis=0)
    shifts -= shifts.mean(axis=0)
    turns *= np.radians(pose_deg) / np.sqrt(np.mean(np.sum(turns**2, axis=1)))
    shifts *= pose_m / np.sqrt(np.mean(np.sum(shifts**2, axis=1)))
    views = []
    for cam, bias, turn, shift in zip(cams, biases, turns, shifts, strict=True):
        depth = sphere_depth(cam, bias, noise_m, rng, spheres=BALLS)
        written = np.asarray(cam.world_from_depth).copy()
        written[:3, :3] = Rotation.from_rotvec(turn).as_matrix() @ written[:3, :3]
        written[:3, 3] += shift
        views.append(DepthView(depth, cam.depth_intrinsics, written))
    return views


def _surface_rms(views: list[DepthView], poses: np.ndarray, offsets: np.ndarray) -> float:
    gaps = []
    for view, pose, offset in zip(views, poses, offsets, strict=True):
        depth = apply_offsets(view.depth_m, ray_image(view.intrinsics), offset)
        pts = register_view(depth, view.intrinsics, pose, None, RegistrationConfig())
        gaps.append(_distance_to_balls(pts.points_world))
    return float(np.sqrt(np.mean(np.concatenate(gaps) ** 2)))


@pytest.mark.parametrize("seed", [0, 1])
def test_range_offsets_between_cameras_are_recovered(seed: int) -> None:
    biases = np.random.default_rng(seed).normal(0, 0.003, size=6)
    found = estimate_corrections(_views(list(biases), noise_m=0.001),
                                 AlignConfig(poses=False))
    offsets = found.offsets_m
    # Differences between cameras are what the overlaps observe best.
    np.testing.assert_allclose(offsets - offsets.mean(), biases - biases.mean(), atol=3e-4)
    assert abs(offsets.mean() - biases.mean()) < 1.5e-3


def test_pose_errors_are_reduced() -> None:
    views = _views([0.002, -0.003, 0.0, 0.001, -0.001, 0.003], noise_m=0.0005,
                   pose_deg=0.25, pose_m=0.003)
    written = np.array([v.world_from_depth for v in views])
    before = _surface_rms(views, written, np.zeros(6))
    found = estimate_corrections(views, AlignConfig())
    after = _surface_rms(views, found.world_from_depth, found.offsets_m)
    assert after < 0.4 * before
    offsets_only = estimate_corrections(views, AlignConfig(poses=False))
    assert after < _surface_rms(views, written, offsets_only.offsets_m)


def test_exact_cameras_stay_put() -> None:
    views = _views([0.0] * 4)
    found = estimate_corrections(views, AlignConfig())
    np.testing.assert_allclose(found.offsets_m, 0.0, atol=2e-4)
    for view, pose in zip(views, found.world_from_depth, strict=True):
        np.testing.assert_allclose(pose, view.world_from_depth, atol=5e-4)


def test_nothing_to_align() -> None:
    views = _views([0.004, -0.004, 0.0, 0.0])
    off = estimate_corrections(views, AlignConfig(offsets=False, poses=False))
    assert np.all(off.offsets_m == 0)
    np.testing.assert_array_equal(off.world_from_depth, [v.world_from_depth for v in views])
    assert estimate_corrections(views[:1], AlignConfig()).offsets_m.tolist() == [0.0]


def test_applying_the_offset_restores_the_true_depth() -> None:
    cam = ring_cameras(1, 160, 144)[0]
    truth = sphere_depth(cam)
    measured = sphere_depth(cam, bias_m=0.005)
    fixed = apply_offsets(measured, ray_image(cam.depth_intrinsics), 0.005)
    assert np.all((fixed > 0) == (truth > 0))
    np.testing.assert_allclose(fixed[truth > 0], truth[truth > 0], atol=1e-5)
