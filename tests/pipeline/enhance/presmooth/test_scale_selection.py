import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.enhance.presmooth.scale_selection import (
    TwicingBlendConfig,
    _twicing_polynomial,
    blend,
    twicing_candidates,
)
from pipeline.enhance.training.data import noisy_along_normals
from pipeline.geometry.smoothing import twicing_smooth
from tests.pipeline.meshes import sphere

SMALL = TwicingBlendConfig(iterations=(2, 5, 10), pilot_iterations=5, feature_rings=(0, 3))


def _noisy_sphere(seed: int = 0):
    return noisy_along_normals(sphere(0.5, 12), 0.03, np.random.default_rng(seed))


def _rotation(angles):
    a, b, c = angles
    rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    rx = np.array([[1, 0, 0], [0, np.cos(c), -np.sin(c)], [0, np.sin(c), np.cos(c)]])
    return rz @ ry @ rx


@settings(max_examples=10, deadline=None)
@given(
    angles=st.tuples(*[st.floats(-np.pi, np.pi)] * 3),
    shift=st.tuples(*[st.floats(-2.0, 2.0)] * 3),
    scale=st.floats(0.1, 10.0),
)
def test_features_ignore_pose_and_scale_and_candidates_follow_them(angles, shift, scale):
    """The selector must weigh a mesh alike wherever it stands and in any unit: features
    are lengths along normals in noise stds, and twicing commutes with similarity transforms."""
    mesh = _noisy_sphere()
    r, t = _rotation(angles), np.array(shift)
    moved = mesh.with_vertices(scale * mesh.vertices_m @ r.T + t)
    a, b = twicing_candidates(mesh, SMALL), twicing_candidates(moved, SMALL)
    assert np.allclose(a.features, b.features, rtol=1e-3, atol=1e-3)
    assert b.noise_std_m == pytest.approx(scale * a.noise_std_m, rel=1e-6)
    assert np.allclose(scale * a.vertices_m @ r.T + t, b.vertices_m, atol=1e-9 * scale + 1e-9)


def test_candidates_are_the_twicings_and_features_have_the_documented_shape():
    mesh = _noisy_sphere()
    c = twicing_candidates(mesh, SMALL)
    assert c.vertices_m.shape == (3, mesh.vertex_count, 3)
    assert c.features.shape == (mesh.vertex_count, SMALL.feature_count)
    for k, v in zip(SMALL.iterations, c.vertices_m, strict=True):
        assert np.allclose(v, twicing_smooth(mesh, k, SMALL.passes).vertices_m)


def test_noise_std_is_estimated():
    """Uniform noise in ±1 cm has a std of 5.77 mm (a sphere of about 4500 vertices, fine
    enough for the pilot's 30 iterations to keep its shape)."""
    mesh = noisy_along_normals(sphere(0.5, 48), 0.01, np.random.default_rng(1))
    c = twicing_candidates(mesh, TwicingBlendConfig())
    assert c.noise_std_m == pytest.approx(0.01 / np.sqrt(3), rel=0.1)


def test_blend_of_one_hot_weights_picks_and_uniform_weights_average():
    c = twicing_candidates(_noisy_sphere(), SMALL)
    v = c.vertices_m.shape[1]
    pick = np.zeros((v, 3))
    pick[:, 1] = 1.0
    assert np.allclose(blend(c.vertices_m, pick), c.vertices_m[1])
    assert np.allclose(blend(c.vertices_m, np.full((v, 3), 1 / 3)), c.vertices_m.mean(axis=0))


def test_torch_steps_give_the_scipy_candidates_and_features():
    """The selector's smoothing steps may run in torch (all cores, or the GPU): the same
    candidates and features as scipy's, to rounding."""
    mesh = _noisy_sphere()
    host, torch_cpu = twicing_candidates(mesh, SMALL), twicing_candidates(mesh, SMALL, "cpu")
    assert np.allclose(torch_cpu.vertices_m, host.vertices_m, rtol=0, atol=1e-12)
    assert np.allclose(torch_cpu.features, host.features, rtol=1e-5, atol=1e-5)
    assert torch_cpu.noise_std_m == pytest.approx(host.noise_std_m, rel=1e-12)


@pytest.mark.skipif(not __import__("torch").cuda.is_available(), reason="no CUDA device")
def test_cuda_steps_give_the_scipy_candidates():
    mesh = _noisy_sphere()
    host, gpu = twicing_candidates(mesh, SMALL), twicing_candidates(mesh, SMALL, "cuda")
    assert np.allclose(gpu.vertices_m, host.vertices_m, rtol=0, atol=1e-12)
    assert np.allclose(gpu.features, host.features, rtol=1e-5, atol=1e-5)


def test_a_count_of_zero_is_the_mesh_itself():
    """No steps twiced is the identity (both passes' terms fall on the power 0)."""
    assert _twicing_polynomial(0, 2) == {0: 1}
    mesh = _noisy_sphere()
    c = twicing_candidates(mesh, TwicingBlendConfig(iterations=(0, 5), pilot_iterations=3,
                                                    feature_rings=(0,)))
    assert np.array_equal(c.vertices_m[0], mesh.vertices_m)
    assert np.allclose(c.vertices_m[1], twicing_smooth(mesh, 5, 2).vertices_m)
