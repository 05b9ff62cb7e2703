import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.enhance.presmooth.scale_selection import (
    TwicingBlendConfig,
    _product,
    _step_polynomials,
    _twicing_polynomial,
    twicing_candidates,
)
from pipeline.enhance.presmooth.scale_selection_numpy import field_ops
from pipeline.enhance.training.data import noisy_along_normals
from pipeline.geometry.boundary import across_boundary, boundary_half_edges, boundary_offset
from pipeline.geometry.mesh import TriangleMesh
from pipeline.geometry.smoothing import mean_operator
from tests.pipeline.meshes import grid, sphere

HOLD = TwicingBlendConfig(iterations=(10, 60), pilot_iterations=10, feature_rings=(0,))
FREE = TwicingBlendConfig(iterations=(10, 60), pilot_iterations=10, feature_rings=(0,),
                          boundary_pilot_iterations=0)


def open_sphere() -> TriangleMesh:
    """A sphere with its top cap cut off (one circular boundary)."""
    s = sphere(0.5, 48)
    keep = s.vertices_m[s.faces].mean(axis=1)[:, 2] < 0.3
    return TriangleMesh(s.vertices_m, s.faces[keep])


def _offset(mesh: TriangleMesh):
    return boundary_offset(mesh, mean_operator(mesh.faces, mesh.vertex_count), 10)


def test_a_closed_mesh_has_no_boundary_and_no_offset():
    s = sphere(0.5, 8)
    assert len(boundary_half_edges(s.faces)) == 0
    assert boundary_offset(s, mean_operator(s.faces, s.vertex_count), 10) is None
    assert boundary_offset(grid(5), mean_operator(grid(5).faces, 25), 0) is None


def test_boundary_half_edges_follow_the_winding_round_a_square():
    n = 6
    faces = grid(n).faces
    half = boundary_half_edges(faces)
    assert len(half) == 4 * (n - 1)
    # Each runs as its one face winds: (a, b) follow each other in that face's corner order.
    wound = {(int(f[c]), int(f[(c + 1) % 3])) for f in faces for c in range(3)}
    assert all((int(a), int(b)) in wound for a, b in half)
    # Each boundary vertex starts exactly one half-edge and ends one: a closed loop.
    assert sorted(half[:, 0]) == sorted(half[:, 1])
    assert len(np.unique(half[:, 0])) == 4 * (n - 1)


def test_across_is_in_the_surface_and_across_the_boundary():
    n = 7
    mesh = grid(n)
    across = across_boundary(mesh.vertices_m, mesh.faces, boundary_half_edges(mesh.faces))
    x, y = mesh.vertices_m[:, 0] / 0.01, mesh.vertices_m[:, 1] / 0.01
    inner = (x > 0.5) & (x < n - 1.5) & (y > 0.5) & (y < n - 1.5)
    assert np.allclose(across[inner], 0.0)
    left = np.isclose(x, 0) & (y > 0.5) & (y < n - 1.5)
    assert np.allclose(np.abs(across[left]), [1.0, 0.0, 0.0], atol=1e-9)
    bottom = np.isclose(y, 0) & (x > 0.5) & (x < n - 1.5)
    assert np.allclose(np.abs(across[bottom]), [0.0, 1.0, 0.0], atol=1e-9)


@settings(max_examples=8, deadline=None)
@given(n=st.integers(8, 16), spacing_m=st.floats(0.002, 0.05), seed=st.integers(0, 100))
def test_held_boundaries_retract_far_less_under_long_twicings(n, spacing_m, seed):
    """A flat noisy square: twicing 60 x 2 steps pulls its free edges inwards by about three
    spacings; with the boundary's one-sided offset (measured on a pilot that has itself
    retracted a little) left out of each step, by about a quarter less (0.72-0.77 of it
    here), never outwards; the surface stays flat either way."""
    clean = grid(n, spacing_m)
    noisy = noisy_along_normals(clean, 0.2 * spacing_m, np.random.default_rng(seed))
    side_m = (n - 1) * spacing_m

    def shrink_m(config: TwicingBlendConfig) -> float:
        v = twicing_candidates(noisy, config).vertices_m[-1]
        extent = v[:, :2].max(axis=0) - v[:, :2].min(axis=0)
        assert np.abs(v[:, 2]).max() < 0.2 * spacing_m
        return float(side_m - extent.min())

    free, held = shrink_m(FREE), shrink_m(HOLD)
    assert free > 2.0 * spacing_m
    assert 0.0 < held < 0.8 * free


def test_a_held_open_sphere_keeps_more_of_its_cap():
    clean = open_sphere()
    noisy = noisy_along_normals(clean, 0.01, np.random.default_rng(0))
    rim = np.unique(boundary_half_edges(clean.faces))
    drop_m = [float(np.mean(clean.vertices_m[rim, 2]
                            - twicing_candidates(noisy, c).vertices_m[-1][rim, 2]))
              for c in (FREE, HOLD)]
    assert drop_m[0] > 0.03
    assert 0.0 < drop_m[1] < 0.8 * drop_m[0]


def test_torch_steps_give_the_scipy_candidates_on_an_open_mesh():
    mesh = noisy_along_normals(open_sphere(), 0.01, np.random.default_rng(0))
    assert _offset(mesh) is not None
    host, torch_cpu = twicing_candidates(mesh, HOLD), twicing_candidates(mesh, HOLD, "cpu")
    assert np.allclose(torch_cpu.vertices_m, host.vertices_m, rtol=0, atol=1e-12)
    assert np.allclose(torch_cpu.features, host.features, rtol=1e-5, atol=1e-5)
    assert torch_cpu.noise_std_m == pytest.approx(host.noise_std_m, rel=1e-12)


def test_the_offset_follows_pose_and_scale():
    mesh = noisy_along_normals(open_sphere(), 0.01, np.random.default_rng(1))
    c, s = np.cos(0.7), np.sin(0.7)
    r = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    moved = mesh.with_vertices(3.0 * mesh.vertices_m @ r.T + 1.0)
    a, b = _offset(mesh), _offset(moved)
    assert a is not None and b is not None
    assert np.allclose(3.0 * a @ r.T, b, atol=1e-12)


@settings(max_examples=10, deadline=None)
@given(n=st.integers(4, 12), k=st.integers(1, 20), pilot=st.integers(1, 15),
       seed=st.integers(0, 2**31 - 1))
def test_a_twicing_of_the_pilot_is_the_product_polynomial_of_the_offset_steps(n, k, pilot, seed):
    """The candidates' features twice the pilot by one run of steps on the mesh alone: with
    the boundary left out each step is affine, and twicings are affine combinations."""
    mesh = noisy_along_normals(grid(n), 0.003, np.random.default_rng(seed))
    m = mean_operator(mesh.faces, mesh.vertex_count)
    ops = field_ops(m, mesh.faces, _offset(mesh))
    p, t = _twicing_polynomial(pilot, 2), _twicing_polynomial(k, 2)
    (pilot_m,) = _step_polynomials(ops.step, mesh.vertices_m, [p])
    (stepped,) = _step_polynomials(ops.step, pilot_m, [t])
    (at_once,) = _step_polynomials(ops.step, mesh.vertices_m, [_product(t, p)])
    assert np.allclose(at_once, stepped, rtol=0, atol=1e-12)
    assert not np.allclose(pilot_m, mesh.vertices_m, rtol=0, atol=1e-6)
