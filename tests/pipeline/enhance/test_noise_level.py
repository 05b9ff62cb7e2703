"""The noise estimate the enhancement gates on: scale-free, near zero on a clean surface,
growing with the noise."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.enhance.noise_level import noise_to_edge_ratio
from pipeline.enhance.training.data import noisy_along_normals
from pipeline.geometry.mesh import TriangleMesh, mean_edge_length_m
from tests.pipeline.meshes import sphere

SPHERE = sphere(0.5, 40)


def _noisy(amplitude_edges: float, seed: int) -> TriangleMesh:
    amplitude_m = amplitude_edges * mean_edge_length_m(SPHERE)
    return noisy_along_normals(SPHERE, amplitude_m, np.random.default_rng(seed))


@settings(max_examples=15, deadline=None)
@given(radius_m=st.floats(0.05, 5.0), resolution=st.integers(12, 48))
def test_a_clean_sphere_reads_as_clean_at_any_size_and_tessellation(
    radius_m: float, resolution: int
) -> None:
    assert noise_to_edge_ratio(sphere(radius_m, resolution)) < 0.03


@settings(max_examples=15, deadline=None)
@given(amplitude_edges=st.floats(0.05, 2.0), seed=st.integers(0, 1000),
       scale=st.floats(0.01, 100.0))
def test_the_ratio_does_not_depend_on_the_unit(amplitude_edges: float, seed: int,
                                                scale: float) -> None:
    mesh = _noisy(amplitude_edges, seed)
    scaled = mesh.with_vertices(mesh.vertices_m * scale)
    assert np.isclose(noise_to_edge_ratio(scaled), noise_to_edge_ratio(mesh), rtol=1e-6)


@settings(max_examples=15, deadline=None)
@given(low=st.floats(0.05, 1.0), seed=st.integers(0, 1000))
def test_more_noise_reads_as_more(low: float, seed: int) -> None:
    assert noise_to_edge_ratio(_noisy(low, seed)) < noise_to_edge_ratio(_noisy(1.5 * low, seed))


def test_the_documented_levels() -> None:
    # Uniform noise of amplitude 0.2 edge lengths: about 0.11 (the gate's neighbourhood).
    assert 0.08 < noise_to_edge_ratio(_noisy(0.2, 0)) < 0.14
    assert noise_to_edge_ratio(_noisy(2.0, 0)) > 0.4


@settings(max_examples=10, deadline=None)
@given(amplitude_edges=st.floats(0.0, 2.0), seed=st.integers(0, 1000))
def test_the_torch_estimate_is_numpys(amplitude_edges: float, seed: int) -> None:
    mesh = _noisy(amplitude_edges, seed)
    assert noise_to_edge_ratio(mesh, "cpu") == pytest.approx(noise_to_edge_ratio(mesh),
                                                              rel=1e-9)
