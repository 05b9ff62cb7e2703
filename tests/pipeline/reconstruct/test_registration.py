from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from pipeline.capture import Intrinsics
from pipeline.reconstruct.registration import (
    RegistrationConfig,
    invert_rigid,
    pixel_rays,
    project,
    ray_image,
    register_view,
    transform,
)
from tests.pipeline.sphere_scene import distance_to_sphere, ring_cameras, sphere_depth

distortions = st.one_of(
    st.just(()),
    st.tuples(st.floats(-0.2, 0.2), st.floats(-0.05, 0.05)),
    st.tuples(st.floats(-0.2, 0.2), st.floats(-0.05, 0.05), st.floats(-0.005, 0.005),
              st.floats(-0.005, 0.005), st.floats(-0.02, 0.02)),
)


@settings(max_examples=60, deadline=None)
@given(distortion=distortions, fx=st.floats(400, 800), aspect=st.floats(0.9, 1.1),
       seed=st.integers(0, 2**31))
def test_back_projection_then_projection_returns_the_pixels(distortion: tuple[float, ...],
                                                            fx: float, aspect: float,
                                                            seed: int) -> None:
    intr = Intrinsics(width=640, height=576, fx=fx, fy=fx * aspect, cx=319.5, cy=287.5,
                      distortion=distortion)
    rng = np.random.default_rng(seed)
    # Normalised radius <= 0.6, where every lens drawn here is monotonic (invertible).
    pixels = rng.uniform([120, 100], [520, 476], size=(50, 2))
    depth = rng.uniform(0.5, 4.0, size=50)
    points = pixel_rays(intr, pixels) * depth[:, None]
    np.testing.assert_allclose(points[:, 2], depth)
    np.testing.assert_allclose(project(intr, points), pixels, atol=1e-4)


def test_ray_image_matches_pixel_rays_without_distortion() -> None:
    intr = Intrinsics(width=8, height=6, fx=5.0, fy=6.0, cx=3.5, cy=2.5)
    ys, xs = np.mgrid[0:6, 0:8]
    expected = pixel_rays(intr, np.column_stack([xs.ravel(), ys.ravel()]).astype(float))
    np.testing.assert_allclose(ray_image(intr).reshape(-1, 3), expected, atol=1e-6)


rotations = st.builds(lambda q: Rotation.from_quat(q).as_matrix(),
                      st.tuples(*[st.floats(-1, 1)] * 4).filter(
                          lambda q: np.linalg.norm(q) > 0.1))


@settings(max_examples=60, deadline=None)
@given(rotation=rotations, translation=st.tuples(*[st.floats(-5, 5)] * 3),
       seed=st.integers(0, 2**31))
def test_world_transforms_invert(rotation: np.ndarray, translation: tuple[float, ...],
                                 seed: int) -> None:
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rotation, translation
    inverse = invert_rigid(pose)
    np.testing.assert_allclose(inverse @ pose, np.eye(4), atol=1e-9)
    points = np.random.default_rng(seed).normal(size=(20, 3))
    np.testing.assert_allclose(transform(inverse, transform(pose, points)), points, atol=1e-9)


@pytest.mark.parametrize("distortion", [(), (0.1, -0.05)])
def test_registered_sphere_points_lie_on_the_sphere_with_outward_normals(
        distortion: tuple[float, ...]) -> None:
    cams = ring_cameras(3, 160, 144, distortion=distortion)
    for cam in cams:
        depth = sphere_depth(cam)
        color = np.zeros((144, 160, 3), dtype=np.uint8)
        color[..., 0] = 7
        pts = register_view(depth, cam.depth_intrinsics, cam.world_from_depth, color,
                            RegistrationConfig())
        assert len(pts.points_world) > 0.5 * np.count_nonzero(depth)
        assert np.abs(distance_to_sphere(pts.points_world)).max() < 1e-4
        radial = pts.points_world - np.array([0.0, 1.0, 0.0])
        radial /= np.linalg.norm(radial, axis=1, keepdims=True)
        cos = np.sum(radial * pts.normals_world, axis=1)
        assert np.median(cos) > 0.999 and cos.min() > 0.9
        assert pts.colors is not None and np.all(pts.colors[:, 0] == 7)
        # Every point comes from the pixel it names.
        x, y = pts.pixels[:, 0], pts.pixels[:, 1]
        assert np.all(depth[y, x] > 0)


def test_grazing_points_are_dropped() -> None:
    cam = ring_cameras(1, 160, 144)[0]
    depth = sphere_depth(cam)
    loose = register_view(depth, cam.depth_intrinsics, cam.world_from_depth, None,
                          RegistrationConfig(max_incidence_deg=89.9))
    strict = register_view(depth, cam.depth_intrinsics, cam.world_from_depth, None,
                           RegistrationConfig(max_incidence_deg=45.0))
    assert len(strict.points_world) < 0.8 * len(loose.points_world)


def test_bad_shapes_are_value_errors() -> None:
    cam = ring_cameras(1, 160, 144)[0]
    with pytest.raises(ValueError, match="depth_m"):
        register_view(np.zeros((10, 10), np.float32), cam.depth_intrinsics,
                      cam.world_from_depth, None, RegistrationConfig())
    with pytest.raises(ValueError, match="color_rgb"):
        register_view(np.zeros((144, 160), np.float32), cam.depth_intrinsics,
                      cam.world_from_depth, np.zeros((10, 10, 3), np.uint8),
                      RegistrationConfig())
