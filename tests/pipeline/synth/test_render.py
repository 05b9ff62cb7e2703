"""Ray-cast rendering: depth matches analytic ray-sphere intersections, colour is registered."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.capture import Intrinsics
from pipeline.geometry.mesh import TriangleMesh
from pipeline.synth.render import MeshRaycaster, pixel_rays, render_depth, shade_color
from pipeline.synth.rig import look_at
from pipeline.synth.shapes import uv_sphere_mesh

RADIUS_M = 0.3
CENTRE_M = np.array([0.1, 0.9, -0.05])
SMALL = Intrinsics(width=96, height=80, fx=90.0, fy=85.0, cx=47.5, cy=39.5)


@pytest.fixture(scope="module")
def sphere_caster() -> MeshRaycaster:
    # Fine enough that the chord error (sagitta) stays near 0.01 mm.
    sphere = uv_sphere_mesh(RADIUS_M, ring_count=200, azimuth_count=400)
    return MeshRaycaster(sphere.with_vertices(sphere.vertices_m + CENTRE_M))


def _analytic_depth(intr: Intrinsics, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(z-depth or inf, cosine of incidence) of rays against the exact sphere."""
    dirs = pixel_rays(intr) @ pose[:3, :3].T
    offset = pose[:3, 3] - CENTRE_M
    a = np.sum(dirs * dirs, axis=-1)
    b = 2 * dirs @ offset
    c = offset @ offset - RADIUS_M**2
    disc = b * b - 4 * a * c
    t = np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.inf)
    normal = pose[:3, 3] + dirs * t[..., None] - CENTRE_M
    cos = np.abs(np.sum(normal * dirs, axis=-1)) / (RADIUS_M * np.sqrt(a))
    return t, np.nan_to_num(cos)


@settings(max_examples=15, deadline=None)
@given(azimuth=st.floats(0, 2 * np.pi), elevation=st.floats(-1.2, 1.2),
       distance=st.floats(0.8, 3.5), aim=st.tuples(*[st.floats(-0.1, 0.1)] * 3))
def test_sphere_depth_matches_ray_sphere_intersection(
        sphere_caster: MeshRaycaster, azimuth: float, elevation: float, distance: float,
        aim: tuple[float, float, float]) -> None:
    direction = np.array([np.cos(elevation) * np.sin(azimuth), np.sin(elevation),
                          np.cos(elevation) * np.cos(azimuth)])
    pose = look_at(CENTRE_M + distance * direction, CENTRE_M + np.array(aim))
    rendering = sphere_caster.render(SMALL, pose)
    expected, cos = _analytic_depth(SMALL, pose)
    # Away from the grazing rim the polyhedron is within its sagitta of the sphere.
    facing = np.isfinite(expected) & (cos > 0.3)
    assert facing.sum() > 50
    assert rendering.hit[facing].all()
    error = np.abs(rendering.depth_m[facing] - expected[facing])
    assert error.max() < 1e-4
    # Outside the sphere's silhouette nothing is hit.
    assert not rendering.hit[~np.isfinite(expected)].any()
    np.testing.assert_array_equal(rendering.depth_m[~rendering.hit], 0.0)
    # Normals turn towards the camera and agree with the sphere's.
    n = rendering.normals_cam[facing]
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-5)
    rays = pixel_rays(SMALL)[facing]
    assert (np.sum(n * rays, axis=-1) < 0).all()


def test_depth_is_z_not_ray_length_on_a_plane() -> None:
    plane = TriangleMesh(vertices_m=np.array([[-5.0, -5, 2], [5, -5, 2], [5, 5, 2], [-5, 5, 2]]),
                         faces=np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int32))
    rendering = render_depth(plane, SMALL, np.eye(4))
    np.testing.assert_allclose(rendering.depth_m, 2.0, atol=1e-6)
    np.testing.assert_allclose(rendering.normals_cam.reshape(-1, 3), [[0, 0, -1]] * (96 * 80),
                               atol=1e-6)
    np.testing.assert_allclose(rendering.points_world[..., 2], 2.0, atol=1e-6)


def test_colour_is_registered_and_has_edges(sphere_caster: MeshRaycaster) -> None:
    pose = look_at(CENTRE_M + np.array([0.0, 0.0, 1.2]), CENTRE_M)
    rendering = sphere_caster.render(SMALL, pose)
    color = shade_color(rendering)
    assert color.shape == (SMALL.height, SMALL.width, 3) and color.dtype == np.uint8
    np.testing.assert_array_equal(color[~rendering.hit], 0)
    lit = color[rendering.hit].astype(float)
    assert lit.mean() > 40
    # The checker gives strong steps between neighbouring pixels on the surface.
    steps = np.abs(np.diff(color.astype(float), axis=1)).sum(axis=-1)
    inside = rendering.hit[:, 1:] & rendering.hit[:, :-1]
    assert (steps[inside] > 60).sum() > 20


def test_render_refuses_distortion_and_bad_pose(sphere_caster: MeshRaycaster) -> None:
    distorted = Intrinsics(96, 80, 90.0, 85.0, 47.5, 39.5, distortion=(0.1,))
    with pytest.raises(ValueError, match="distortion"):
        sphere_caster.render(distorted, np.eye(4))
    with pytest.raises(ValueError, match="world_from_depth"):
        sphere_caster.render(SMALL, np.eye(3))
