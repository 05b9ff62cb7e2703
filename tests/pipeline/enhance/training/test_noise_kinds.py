"""The protocol's noise models: uniform in ±a (as it always was), Gaussian and Laplace of the
same standard deviation, a / √3."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.enhance.training.data import NOISE_KINDS, noisy_along_normals, normal_offsets_m
from pipeline.geometry.mesh import vertex_normals
from tests.pipeline.meshes import sphere


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**16), amplitude_m=st.floats(1e-4, 0.05))
def test_uniform_noise_is_the_draw_the_protocol_always_made(seed, amplitude_m):
    mesh = sphere(0.5, 16)
    out = noisy_along_normals(mesh, amplitude_m, np.random.default_rng(seed))
    rng = np.random.default_rng(seed)
    n = vertex_normals(mesh.vertices_m, mesh.faces).astype(np.float64)
    before = mesh.vertices_m + n * rng.uniform(-amplitude_m, amplitude_m, (mesh.vertex_count, 1))
    assert np.array_equal(out.vertices_m, before)


@pytest.mark.parametrize(("kind", "kurtosis"), [("uniform", 1.8), ("gaussian", 3.0),
                                                ("laplace", 6.0)])
def test_every_kind_has_the_uniform_noises_standard_deviation(kind, kurtosis):
    offsets = normal_offsets_m(kind, 0.01, np.random.default_rng(0), 400_000)[:, 0]
    assert offsets.std() == pytest.approx(0.01 / np.sqrt(3.0), rel=0.01)
    assert abs(offsets.mean()) < 1e-4
    # Kurtosis tells them apart: Laplace's tails are the heavy ones.
    assert np.mean(offsets**4) / offsets.var() ** 2 == pytest.approx(kurtosis, rel=0.05)
    if kind == "uniform":
        assert np.abs(offsets).max() <= 0.01


def test_the_kinds_are_seeded_and_an_unknown_kind_fails():
    for kind in NOISE_KINDS:
        a = normal_offsets_m(kind, 0.01, np.random.default_rng(3), 50)
        assert np.array_equal(a, normal_offsets_m(kind, 0.01, np.random.default_rng(3), 50))
    with pytest.raises(ValueError, match="uniform, gaussian, laplace"):
        normal_offsets_m("cauchy", 0.01, np.random.default_rng(0), 5)  # type: ignore[arg-type]
