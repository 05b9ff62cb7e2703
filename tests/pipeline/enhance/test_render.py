import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.enhance.render import make_views, project, render_depth, view_directions


def test_axis_views_first_then_spread():
    six = view_directions(6)
    assert np.allclose(six[0], [0, 0, -1]) and np.allclose(six[4], [0, -1, 0])
    many = view_directions(26)
    assert many.shape == (26, 3)
    assert np.allclose(np.linalg.norm(many, axis=1), 1.0)
    with pytest.raises(ValueError, match="views"):
        view_directions(0)


def test_camera_frames_are_right_handed_opencv():
    views = make_views(np.random.default_rng(0).normal(size=(50, 3)), view_directions(14), 32)
    cross = np.cross(views.rights, views.downs)
    assert np.allclose(cross, views.forwards, atol=1e-9)


def test_sphere_depth_matches_geometry(unit_sphere):
    views = make_views(unit_sphere.vertices_m, view_directions(6), 64)
    r = render_depth(unit_sphere, views)
    # The sphere's nearest point is (R_box - 0.5 m) from the near plane, in units of 2 R_box.
    expected_min = (views.half_extent_m - 0.5) / views.depth_range_m
    assert r.depth_n[r.valid].min() == pytest.approx(expected_min, abs=2e-3)
    # Silhouette area close to the disc's.
    pixel_m = 2 * views.half_extent_m / 64
    area = r.valid[0].sum() * pixel_m**2
    assert area == pytest.approx(np.pi * 0.5**2, rel=0.05)
    assert r.color_rgb is None


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 5), st.floats(0.05, 20.0))
def test_rendered_hits_project_back_to_their_pixel(view, scale):
    from tests.pipeline.enhance.conftest import sphere

    mesh = sphere(0.5 * scale, 16)
    views = make_views(mesh.vertices_m, view_directions(6), 32)
    r = render_depth(mesh, views)
    rows, cols = np.nonzero(r.valid[view])
    h = views.half_extent_m
    s = ((np.arange(32) + 0.5) / 32 * 2 - 1) * h
    points = (
        views.center_m
        - views.forwards[view] * h
        + s[cols, None] * views.rights[view]
        + s[rows, None] * views.downs[view]
        + (r.depth_n[view][rows, cols] * views.depth_range_m)[:, None] * views.forwards[view]
    )
    pix, depth = project(points, views)
    assert np.allclose(pix[view, :, 0], cols, atol=1e-3)
    assert np.allclose(pix[view, :, 1], rows, atol=1e-3)
    assert np.allclose(depth[view], r.depth_n[view][rows, cols], atol=1e-4)


def test_vertex_colours_are_interpolated(unit_sphere):
    colored = unit_sphere.__class__(
        unit_sphere.vertices_m,
        unit_sphere.faces,
        vertex_colors=np.full((unit_sphere.vertex_count, 3), 200, np.uint8),
    )
    views = make_views(colored.vertices_m, view_directions(2), 16)
    r = render_depth(colored, views)
    assert r.color_rgb is not None
    assert np.all(np.abs(r.color_rgb[r.valid].astype(int) - 200) <= 1)
    assert np.all(r.color_rgb[~r.valid] == 0)


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="resolution"):
        make_views(np.zeros((3, 3)) + np.eye(3), view_directions(1), 4)
    with pytest.raises(ValueError, match="degenerate"):
        make_views(np.zeros((3, 3)), view_directions(1), 16)
