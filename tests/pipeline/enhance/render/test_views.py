import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.enhance.render.views import (
    DepthRenders,
    make_views,
    project,
    render_depth,
    view_directions,
)
from pipeline.geometry.mesh import TriangleMesh


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
    from tests.pipeline.meshes import sphere

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


# The torch rasterizer against open3d's ray cast: the same pixels, depths and colours, but for
# pixel centres that fall exactly on an edge (a silhouette's, or a rim's with more surface
# behind), where either may count the hit.

def _coloured(mesh, seed=0):
    colors = np.random.default_rng(seed).integers(0, 256, (mesh.vertex_count, 3), np.uint8)
    return TriangleMesh(mesh.vertices_m, mesh.faces, vertex_colors=colors)


def _assert_agrees(ray_cast, rasterized, max_disagreeing=0.002):
    assert ray_cast.depth_n.dtype == rasterized.depth_n.dtype == np.float32
    assert rasterized.valid.shape == ray_cast.valid.shape
    both = ray_cast.valid & rasterized.valid
    same_depth = np.abs(ray_cast.depth_n - rasterized.depth_n) <= 1e-5
    agree = (ray_cast.valid == rasterized.valid) & (same_depth | ~both)
    assert np.mean(~agree) <= max_disagreeing
    assert (both & same_depth).sum() > 0.95 * ray_cast.valid.sum()
    assert np.all(rasterized.depth_n[~rasterized.valid] == 1.0)
    if ray_cast.color_rgb is None:
        assert rasterized.color_rgb is None
        return
    assert rasterized.color_rgb is not None and rasterized.color_rgb.dtype == np.uint8
    diff = np.abs(ray_cast.color_rgb.astype(int) - rasterized.color_rgb.astype(int))
    assert diff[both & same_depth].max() <= 1
    assert np.all(rasterized.color_rgb[~rasterized.valid] == 0)


def _open_bowl():
    """A sphere with its cap above z = 0.2 cut off: an open boundary, inside faces visible."""
    from tests.pipeline.meshes import sphere

    whole = sphere(0.5, 20)
    keep = whole.vertices_m[whole.faces].mean(axis=1)[:, 2] < 0.2
    return TriangleMesh(whole.vertices_m, whole.faces[keep])


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_rasterizer_matches_ray_cast_on_sphere(unit_sphere, dtype):
    import torch

    from pipeline.enhance.render.rasterize import rasterize_depth

    mesh = _coloured(unit_sphere)
    views = make_views(mesh.vertices_m, view_directions(14), 64)
    depth, valid, color = rasterize_depth(
        mesh.vertices_m, mesh.faces, views, "cpu", mesh.vertex_colors,
        dtype=getattr(torch, dtype))
    _assert_agrees(render_depth(mesh, views), DepthRenders(views, depth, valid, color))


def test_rasterizer_matches_ray_cast_on_open_boundary():
    mesh = _coloured(_open_bowl(), seed=1)
    views = make_views(mesh.vertices_m, view_directions(10), 80)
    _assert_agrees(render_depth(mesh, views), render_depth(mesh, views, device="cpu"))
    _assert_agrees(render_depth(mesh, views, with_color=False),
                   render_depth(mesh, views, with_color=False, device="cpu"))


def test_rasterizer_drops_what_lies_before_the_near_plane():
    from tests.pipeline.meshes import sphere

    # Views fitted to a smaller sphere: the larger one crosses every near plane, so the
    # rays (and the rasterizer) see its inside through the cut.
    views = make_views(sphere(0.4, 16).vertices_m, view_directions(6), 48)
    mesh = _coloured(sphere(0.5, 24))
    ray_cast = render_depth(mesh, views)
    _assert_agrees(ray_cast, render_depth(mesh, views, device="cpu"))
    # The centre ray starts inside the sphere and meets its far side past the depth range.
    assert np.all(ray_cast.valid[:, 24, 24]) and np.all(ray_cast.depth_n[:, 24, 24] == 1.0)


def test_rasterizer_chunks_give_the_same_renders():
    from pipeline.enhance.render.rasterize import rasterize_depth

    mesh = _coloured(_open_bowl())
    views = make_views(mesh.vertices_m, view_directions(3), 40)
    whole = rasterize_depth(mesh.vertices_m, mesh.faces, views, "cpu", mesh.vertex_colors)
    chunked = rasterize_depth(mesh.vertices_m, mesh.faces, views, "cpu", mesh.vertex_colors,
                              max_candidates=50)
    for a, b in zip(whole, chunked, strict=True):
        assert np.array_equal(a, b)


def _rotation(q):
    w, x, y, z = np.asarray(q) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


@settings(max_examples=10, deadline=None)
@given(
    st.lists(st.floats(-1.0, 1.0), min_size=4, max_size=4).filter(
        lambda q: np.linalg.norm(q) > 0.1),
    st.floats(0.05, 20.0),
    st.lists(st.floats(-5.0, 5.0), min_size=3, max_size=3),
    st.integers(1, 9),
    st.integers(0, 1000),
)
def test_rasterizer_matches_ray_cast_in_any_pose(quaternion, scale, shift, n_views, seed):
    bowl = _open_bowl()
    bumpy = bowl.vertices_m + np.random.default_rng(seed).normal(0, 0.02, bowl.vertices_m.shape)
    # The shift is in the mesh's own size: far from the origin, float32 ray origins would lose
    # the depth precision the comparison asks for.
    vertices_m = scale * (bumpy @ _rotation(quaternion).T + np.asarray(shift))
    mesh = _coloured(TriangleMesh(vertices_m, bowl.faces), seed)
    views = make_views(mesh.vertices_m, view_directions(n_views), 48)
    _assert_agrees(render_depth(mesh, views), render_depth(mesh, views, device="cpu"))


@pytest.mark.skipif(
    not __import__("torch").cuda.is_available(), reason="needs a CUDA device")
def test_rasterizer_on_cuda_matches_cpu(unit_sphere):
    mesh = _coloured(unit_sphere)
    views = make_views(mesh.vertices_m, view_directions(8), 64)
    _assert_agrees(render_depth(mesh, views, device="cpu"),
                   render_depth(mesh, views, device="cuda"))
