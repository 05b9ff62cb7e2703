from collections import deque

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.enhance import EnhanceConfig
from pipeline.enhance.config import validate_config
from pipeline.enhance.presmooth.midrange import (
    BoundedNoiseConfig,
    bounded_noise_refine,
    residual_kurtosis,
)
from pipeline.enhance.presmooth.midrange_numpy import closed_neighbourhoods, neighbourhood_range
from pipeline.enhance.training.data import noisy_along_normals
from pipeline.geometry.mesh import TriangleMesh
from pipeline.geometry.smoothing import twicing_smooth
from tests.pipeline.geometry.test_boundary import grid
from tests.pipeline.meshes import radial_rms_m, sphere

SEEDS = st.integers(0, 2**31 - 1)


@given(seed=SEEDS)
@settings(max_examples=10, deadline=None)
def test_kurtosis_tells_uniform_from_gaussian_noise(seed):
    rng = np.random.default_rng(seed)
    uniform = residual_kurtosis(rng.uniform(-0.01, 0.01, 20_000))
    gaussian = residual_kurtosis(rng.normal(0.0, 0.01, 20_000))
    limit = BoundedNoiseConfig().max_kurtosis
    assert abs(uniform - 1.8) < 0.1 and uniform < limit
    assert abs(gaussian - 3.0) < 0.3 and gaussian > limit


def test_residuals_all_alike_have_no_finite_kurtosis():
    assert residual_kurtosis(np.full(10, 0.003)) == float("inf")


def _ring_range(faces, values, vertex, rings):
    """Least and greatest of `values` within `rings` rings of `vertex`, by breadth-first search."""
    neighbours = {i: set() for i in range(len(values))}
    for a, b, c in faces:
        for p, q in ((a, b), (b, c), (c, a)):
            neighbours[int(p)].add(int(q))
            neighbours[int(q)].add(int(p))
    depth, queue = {vertex: 0}, deque([vertex])
    while queue:
        u = queue.popleft()
        for w in neighbours[u]:
            if w not in depth and depth[u] < rings:
                depth[w] = depth[u] + 1
                queue.append(w)
    found = values[list(depth)]
    return found.min(), found.max()


@given(seed=SEEDS, rings=st.integers(0, 3))
@settings(max_examples=15, deadline=None)
def test_neighbourhood_range_is_the_range_within_the_rings(seed, rings):
    mesh = grid(6)
    values = np.random.default_rng(seed).normal(size=mesh.vertex_count)
    low, high = neighbourhood_range(values, closed_neighbourhoods(mesh.faces, 36), rings)
    for vertex in range(mesh.vertex_count):
        assert (low[vertex], high[vertex]) == _ring_range(mesh.faces, values, vertex, rings)


def _biased_plane(bias_m: float, noise, seed: int):
    """(truth, noisy, smooth): a flat 30 x 30 grid at z = 0, the grid moved along +z by `noise`
    draws, and the flat grid lifted by `bias_m` (a smooth estimate with a constant error)."""
    truth = grid(30)
    rng = np.random.default_rng(seed)
    noisy = truth.with_vertices(truth.vertices_m + [0.0, 0.0, 1.0] * noise(rng, (900, 1)))
    smooth = truth.with_vertices(truth.vertices_m + [0.0, 0.0, bias_m])
    return truth, noisy, smooth


@given(seed=SEEDS, amplitude_mm=st.floats(2.0, 10.0), bias_share=st.floats(-0.5, 0.5))
@settings(max_examples=15, deadline=None)
def test_uniform_noise_takes_a_biased_estimate_back_to_the_plane(seed, amplitude_mm, bias_share):
    a = amplitude_mm / 1000

    def uniform(rng, shape):
        return rng.uniform(-a, a, shape)

    _, noisy, smooth = _biased_plane(bias_share * a, uniform, seed)
    refined = bounded_noise_refine(noisy, smooth, BoundedNoiseConfig())
    rms_m = np.sqrt(np.mean(refined.vertices_m[:, 2] ** 2))
    # The average of the noise over three rings (37 vertices) errs by a / sqrt(3 * 37), about
    # 0.095 a; the range's middle by several times less.
    assert rms_m < 0.06 * a
    np.testing.assert_array_equal(refined.vertices_m[:, :2], smooth.vertices_m[:, :2])


@given(seed=SEEDS)
@settings(max_examples=10, deadline=None)
def test_gaussian_noise_leaves_the_estimate_as_it_is(seed):
    def gaussian(rng, shape):
        return rng.normal(0.0, 0.005, shape)

    _, noisy, smooth = _biased_plane(0.002, gaussian, seed)
    refined = bounded_noise_refine(noisy, smooth, BoundedNoiseConfig())
    np.testing.assert_array_equal(refined.vertices_m, smooth.vertices_m)


def test_no_rings_is_off():
    _, noisy, smooth = _biased_plane(0.002, lambda rng, shape: rng.uniform(-0.01, 0.01, shape), 0)
    assert bounded_noise_refine(noisy, smooth, BoundedNoiseConfig(rings=0)) is smooth


def _sphere_errors_m(seed: int) -> tuple[float, float]:
    """The radial RMS of a noisy sphere's twicing and of its bounded-noise refinement."""
    clean = sphere(0.5, 64)
    noisy = noisy_along_normals(clean, 0.01, np.random.default_rng(seed))
    smooth = twicing_smooth(noisy, 10)
    refined = bounded_noise_refine(noisy, smooth, BoundedNoiseConfig())
    return radial_rms_m(smooth), radial_rms_m(refined)


@given(seed=SEEDS)
@settings(max_examples=5, deadline=None)
def test_a_noisy_sphere_comes_back_closer_than_its_smoothing(seed):
    smooth_m, refined_m = _sphere_errors_m(seed)
    assert refined_m < 0.9 * smooth_m


def test_the_refinement_takes_a_sixth_off_the_smoothings_error():
    """Over ten noise draws; single draws may gain less than the mean, hence the mean."""
    errors_m = np.array([_sphere_errors_m(seed) for seed in range(10)])
    assert np.mean(errors_m[:, 1] / errors_m[:, 0]) < 0.85
    assert errors_m[:, 1].max() < 0.0011


def test_a_negative_ring_count_is_named():
    with pytest.raises(ValueError, match="bounded_noise"):
        validate_config(EnhanceConfig(bounded_noise=BoundedNoiseConfig(rings=-1)))


@pytest.mark.parametrize("open_boundary", [False, True])
def test_the_torch_refinement_is_numpys(open_boundary):
    """The torch implementation (`midrange_torch`), run on the CPU, moves the vertices as
    numpy and scipy do, to rounding."""
    from tests.pipeline.geometry.test_boundary import open_sphere

    truth = sphere(0.5, 40)
    if open_boundary:  # the cut sphere without the cap's vertices, which no face uses
        cut = open_sphere()
        used, faces = np.unique(cut.faces, return_inverse=True)
        truth = TriangleMesh(cut.vertices_m[used], faces.reshape(-1, 3).astype(np.int32))
    noisy = noisy_along_normals(truth, 0.01, np.random.default_rng(3))
    smooth = twicing_smooth(noisy, 20)
    config = BoundedNoiseConfig()
    host = bounded_noise_refine(noisy, smooth, config)
    assert not np.allclose(host.vertices_m, smooth.vertices_m)
    torch_cpu = bounded_noise_refine(noisy, smooth, config, "cpu")
    np.testing.assert_allclose(torch_cpu.vertices_m, host.vertices_m, rtol=0, atol=1e-12)


def _selector_presmoothed(noisy: TriangleMesh, config: BoundedNoiseConfig | None
                          ) -> TriangleMesh:
    from pipeline.enhance.inference import selector_presmoothed
    from pipeline.enhance.weights import shipped_bytes
    from pipeline.enhance.weights.loading import load_selector

    return selector_presmoothed(noisy, load_selector(shipped_bytes("selector")), config)


def test_where_the_refinement_does_not_run_the_selectors_blend_is_kept():
    """Gaussian noise: the refinement stays off, and the output is the selector's blend."""
    rng = np.random.default_rng(0)
    clean = sphere(0.5, 64)
    from pipeline.geometry.mesh import vertex_normals

    normals = vertex_normals(clean.vertices_m, clean.faces).astype(np.float64)
    noisy = clean.with_vertices(clean.vertices_m
                                + normals * rng.normal(0.0, 0.005, (clean.vertex_count, 1)))
    blended = _selector_presmoothed(noisy, None)
    np.testing.assert_array_equal(_selector_presmoothed(noisy, BoundedNoiseConfig()).vertices_m,
                                  blended.vertices_m)
