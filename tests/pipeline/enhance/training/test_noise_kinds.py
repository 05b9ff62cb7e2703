"""The protocol's noise models: uniform in ±a (as it always was), Gaussian and Laplace of the
same standard deviation, a / √3."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.enhance.self_check import residuals_m
from pipeline.enhance.training.data import (
    NOISE_KINDS,
    noise_kind,
    noisy_along_normals,
    normal_offsets_m,
    unit_extent,
)
from pipeline.enhance.training.plan import run_config
from pipeline.enhance.training.selector import noisy_draw
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


def test_one_kind_draws_nothing_and_several_draw_each():
    rng = np.random.default_rng(5)
    assert noise_kind(("laplace",), rng) == "laplace"
    assert rng.random() == np.random.default_rng(5).random()  # the stream went untouched
    drawn = {noise_kind(NOISE_KINDS, rng) for _ in range(60)}
    assert drawn == set(NOISE_KINDS)
    with pytest.raises(ValueError, match="noise kinds"):
        noise_kind(("cauchy",), rng)  # type: ignore[arg-type]


@pytest.mark.parametrize(("kind", "heavy"), [("uniform", False), ("laplace", True)])
def test_a_draw_has_the_noise_model_it_was_given(kind, heavy):
    unit = unit_extent(sphere(0.5, 24), "sphere")
    truth, noisy = noisy_draw(unit, (0.03, 0.03), (1.0, 1.0), np.random.default_rng(0), (kind,))
    offsets = residuals_m(noisy, truth)
    kurtosis = np.mean(offsets**4) / offsets.var() ** 2
    assert (kurtosis > 4.5) if heavy else (kurtosis < 2.2)


def test_the_noise_option_sets_every_stage_and_refuses_unknown_models():
    cfg = run_config("tiny", noise="gaussian, laplace")
    assert cfg.data.noise_kinds == cfg.selector.noise_kinds == cfg.gain.noise_kinds \
        == ("gaussian", "laplace")
    assert run_config("tiny").data.noise_kinds == NOISE_KINDS
    with pytest.raises(ValueError, match="--noise"):
        run_config("tiny", noise="gaussian,cauchy")
