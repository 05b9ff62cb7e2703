import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.enhance.render import make_views, render_depth, view_directions
from pipeline.enhance.update import UpdateConfig, unfolded, update_vertices
from pipeline.mesh import face_normals
from tests.pipeline.enhance.conftest import radial_rms_m, sphere


def test_clean_depth_pulls_noisy_vertices_onto_the_surface(noisy_sphere):
    clean, noisy = noisy_sphere
    views = make_views(noisy.vertices_m, view_directions(6), 128)
    r_noisy = render_depth(noisy, views)
    r_clean = render_depth(clean, views)
    out, seen = update_vertices(noisy, r_noisy, r_clean.depth_n, UpdateConfig())
    before = radial_rms_m(noisy)
    after = radial_rms_m(out)
    assert before > 0.004
    # The flat-faceted sphere itself deviates ~1 mm from the ideal one; stay near that.
    assert after < 0.35 * before
    assert seen.mean() > 0.5
    assert np.array_equal(out.faces, noisy.faces)


def test_own_depth_moves_little(noisy_sphere):
    _, noisy = noisy_sphere
    views = make_views(noisy.vertices_m, view_directions(6), 128)
    r = render_depth(noisy, views)
    out, seen = update_vertices(noisy, r, r.depth_n, UpdateConfig(unseen_iterations=0))
    step = np.linalg.norm(out.vertices_m - noisy.vertices_m, axis=1)
    assert np.median(step[seen]) < 0.002


def test_step_is_capped(noisy_sphere):
    _, noisy = noisy_sphere
    views = make_views(noisy.vertices_m, view_directions(6), 64)
    r = render_depth(noisy, views)
    far = np.where(r.valid, r.depth_n + 0.01, r.depth_n).astype(np.float32)
    cfg = UpdateConfig(max_step_fraction=0.005, unseen_iterations=0)
    out, _ = update_vertices(noisy, r, far, cfg)
    step = np.linalg.norm(out.vertices_m - noisy.vertices_m, axis=1)
    assert step.max() <= 0.005 * views.half_extent_m + 1e-9


def test_shape_mismatch_is_named(noisy_sphere):
    _, noisy = noisy_sphere
    views = make_views(noisy.vertices_m, view_directions(2), 32)
    r = render_depth(noisy, views)
    with pytest.raises(ValueError, match="enhanced_depth_n"):
        update_vertices(noisy, r, r.depth_n[:1], UpdateConfig())


def test_unseen_vertices_follow_their_neighbours_moves_on_a_smooth_mesh():
    """Two views leave the back of a clean sphere unseen. Smoothing the unseen positions
    flattens it; following the seen neighbours' (here zero) moves keeps it on the sphere."""
    mesh = sphere(0.5, 24)
    views = make_views(mesh.vertices_m, view_directions(2), 96)
    r = render_depth(mesh, views)
    follow, seen = update_vertices(mesh, r, r.depth_n, UpdateConfig(unseen_follow_moves=True))
    smoothed, _ = update_vertices(mesh, r, r.depth_n, UpdateConfig())
    assert 0.2 < (~seen).mean() < 0.8

    def radial_error(m):
        return np.abs(np.linalg.norm(m.vertices_m, axis=1) - 0.5)[~seen].max()

    assert radial_error(follow) < 0.002
    assert radial_error(smoothed) > 5 * radial_error(follow)


def test_following_the_change_keeps_the_mesh_where_nothing_changed_and_moves_it_by_a_change(
    noisy_sphere,
):
    """Own depth as the enhanced depth: moving to it shifts vertices by the render's lookup
    error, following its change (zero) shifts none; a uniform change of d moves the seen
    vertices by d along the rays."""
    _, noisy = noisy_sphere
    views = make_views(noisy.vertices_m, view_directions(6), 128)
    r = render_depth(noisy, views)
    cfg = UpdateConfig(unseen_iterations=0, follow_change=True)
    same, seen = update_vertices(noisy, r, r.depth_n, cfg)
    assert np.array_equal(same.vertices_m, noisy.vertices_m)
    absolute, _ = update_vertices(noisy, r, r.depth_n, UpdateConfig(unseen_iterations=0))
    assert np.abs(absolute.vertices_m - noisy.vertices_m).max() > 1e-4
    d = 0.001 / views.depth_range_m  # 1 mm farther from every camera
    farther = np.where(r.valid, r.depth_n + d, r.depth_n).astype(np.float32)
    moved, seen = update_vertices(noisy, r, farther, cfg)
    radial = np.linalg.norm(moved.vertices_m, axis=1) - np.linalg.norm(noisy.vertices_m, axis=1)
    # Farther along views that look at the sphere is inwards; averaged over the views that
    # see a vertex, a little less than 1 mm.
    assert np.median(radial[seen]) == pytest.approx(-0.001, abs=3e-4)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), scale_m=st.floats(0.001, 0.2))
def test_no_face_is_left_turned_over_and_every_vertex_is_where_it_was_or_went(seed, scale_m):
    """Random moves up to several edge lengths fold many faces; `unfolded` puts back just the
    corners it must."""
    mesh = sphere(0.5, 12)
    before = mesh.vertices_m
    after = before + np.random.default_rng(seed).normal(scale=scale_m, size=before.shape)
    out = unfolded(before, after, mesh.faces)
    dots = np.sum(face_normals(out, mesh.faces) * face_normals(before, mesh.faces), axis=1)
    assert (dots >= 0).all()
    assert (np.all(out == before, axis=1) | np.all(out == after, axis=1)).all()


def test_a_move_that_turns_a_face_over_is_put_back_and_a_harmless_one_kept():
    mesh = sphere(0.5, 12)
    before = mesh.vertices_m
    after = before.copy()
    tip = mesh.faces[0, 0]
    after[tip] += [0.3, 0.0, 0.0]  # sideways past its ring: the fan's far side turns over
    far = int(np.argmax(np.linalg.norm(before - before[tip], axis=1)))
    after[far] *= 1.001  # a millimetre out
    out = unfolded(before, after, mesh.faces)
    assert np.array_equal(out[tip], before[tip]) and np.array_equal(out[far], after[far])


def test_a_uniform_vertex_gain_moves_as_far_as_that_share_of_the_change(noisy_sphere):
    """Following the change, a vertex gain g on every vertex moves the mesh as the depth change
    scaled by g does (the step is linear in the change); gain 1 is no gain at all."""
    from pipeline.enhance.update import apply_view_steps, view_steps

    _, noisy = noisy_sphere
    views = make_views(noisy.vertices_m, view_directions(6), 128)
    r = render_depth(noisy, views)
    cfg = UpdateConfig(unseen_iterations=0, follow_change=True)
    rng = np.random.default_rng(3)
    change = (rng.normal(size=r.depth_n.shape) * 0.002 / views.depth_range_m).astype(np.float32)
    enhanced = np.where(r.valid, r.depth_n + change, r.depth_n).astype(np.float32)
    steps = view_steps(noisy, r, enhanced, cfg)
    ones = np.ones(noisy.vertex_count)
    plain, seen = apply_view_steps(noisy, steps, cfg)
    assert np.array_equal(apply_view_steps(noisy, steps, cfg, ones)[0].vertices_m,
                          plain.vertices_m)
    assert np.array_equal(plain.vertices_m, update_vertices(noisy, r, enhanced, cfg)[0].vertices_m)
    scaled = np.where(r.valid, r.depth_n + 0.3 * change, r.depth_n).astype(np.float32)
    by_depth, _ = update_vertices(noisy, r, scaled, cfg)
    by_gain, _ = apply_view_steps(noisy, steps, cfg, 0.3 * ones)
    assert np.allclose(by_gain.vertices_m, by_depth.vertices_m, atol=1e-9)
    assert np.abs(by_gain.vertices_m - noisy.vertices_m)[seen].max() > 1e-4
