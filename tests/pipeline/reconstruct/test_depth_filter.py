from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.reconstruct.depth_filter import (
    DepthFilterConfig,
    apply_range,
    bilateral,
    filter_depth,
    local_noise_m,
    remove_flying_pixels,
)

FOCAL = 500.0


def test_range_limits_and_non_finite_values_become_invalid() -> None:
    depth = np.array([[0.1, 1.0, 9.0], [np.nan, np.inf, 2.0]], dtype=np.float32)
    out = apply_range(depth, DepthFilterConfig(min_depth_m=0.25, max_depth_m=5.5))
    np.testing.assert_array_equal(out, [[0, 1.0, 0], [0, 0, 2.0]])


@settings(max_examples=30, deadline=None)
@given(depth=st.floats(0.6, 4.0), gx=st.floats(-0.002, 0.002), gy=st.floats(-0.002, 0.002),
       seed=st.integers(0, 2**31))
def test_bilateral_keeps_planes_and_never_fills_holes(depth: float, gx: float, gy: float,
                                                      seed: int) -> None:
    ys, xs = np.mgrid[0:40, 0:50]
    plane = (depth + gx * xs + gy * ys).astype(np.float32)
    holes = np.random.default_rng(seed).random(plane.shape) < 0.2
    plane[holes] = 0
    out = bilateral(plane, DepthFilterConfig())
    assert np.all((out > 0) == (plane > 0))
    # A linear ramp is its own weighted average away from the border and the holes.
    inner = (slice(3, -3), slice(3, -3))
    full = bilateral(np.where(holes, (depth + gx * xs + gy * ys), plane).astype(np.float32),
                     DepthFilterConfig())
    np.testing.assert_allclose(full[inner], (depth + gx * xs + gy * ys)[inner], atol=2e-5)


def test_bilateral_reduces_noise_and_keeps_steps_sharp() -> None:
    rng = np.random.default_rng(0)
    clean = np.full((60, 60), 2.0, dtype=np.float32)
    clean[:, 30:] = 2.3  # a 30 cm step
    noisy = clean + rng.normal(0, 0.002, clean.shape).astype(np.float32)
    out = bilateral(noisy, DepthFilterConfig())
    inner = (slice(4, -4), slice(4, -4))
    assert np.std((out - clean)[inner]) < 0.5 * np.std((noisy - clean)[inner])
    # Nothing is averaged across the step.
    assert np.abs(out - clean).max() < 0.01


def test_flying_pixels_between_foreground_and_background_are_removed() -> None:
    depth = np.full((20, 20), 3.0, dtype=np.float32)
    depth[:, :10] = 1.5
    depth[:, 10] = 2.2  # mixed pixels on the edge
    out = remove_flying_pixels(depth, FOCAL, DepthFilterConfig())
    assert np.all(out[:, 10] == 0)
    assert np.all(out[:, :10] == 1.5)  # the nearer surface keeps its silhouette


def test_slanted_surfaces_are_not_flying_pixels() -> None:
    xs = np.arange(30, dtype=np.float32)
    # 60 degrees against the view at 2 m: steps of tan(60) * footprint.
    depth = np.tile(2.0 + xs * np.float32(np.tan(np.radians(60)) * 2.0 / FOCAL), (20, 1))
    out = remove_flying_pixels(depth.astype(np.float32), FOCAL, DepthFilterConfig())
    assert np.count_nonzero(out[1:-1, 1:-1]) == out[1:-1, 1:-1].size


def test_a_noisy_far_surface_is_not_flying_pixels() -> None:
    """A structured-light sensor at 4.5 m: noise of centimetres, jumps beyond four
    footprints between neighbours all over the surface, so they are its noise."""
    rng = np.random.default_rng(0)
    depth = (4.5 + rng.normal(0, 0.015, (60, 60))).astype(np.float32)
    kept = remove_flying_pixels(depth, FOCAL, DepthFilterConfig())[1:-1, 1:-1]
    assert np.count_nonzero(kept) > 0.97 * kept.size
    every_jump = remove_flying_pixels(depth, FOCAL, DepthFilterConfig(flying_noise_factor=0))
    assert np.count_nonzero(every_jump[1:-1, 1:-1]) < 0.9 * kept.size


@settings(max_examples=20, deadline=None)
@given(sigma_m=st.floats(0.0005, 0.03), slope=st.floats(-0.01, 0.01), seed=st.integers(0, 99))
def test_the_local_noise_is_the_depth_noise(sigma_m: float, slope: float, seed: int) -> None:
    rng = np.random.default_rng(seed)
    xs = np.arange(80, dtype=np.float32)
    plane = np.tile(3.0 + slope * xs, (80, 1))
    depth = (plane + rng.normal(0, sigma_m, plane.shape)).astype(np.float32)
    noise = local_noise_m(depth)[6:-6, 6:-6]
    assert 0.6 * sigma_m < np.median(noise) < 1.5 * sigma_m


@pytest.mark.parametrize("slanted", [False, True])
def test_mixed_pixels_along_an_edge_are_removed(slanted: bool) -> None:
    rng = np.random.default_rng(1)
    ys, xs = np.mgrid[0:40, 0:40]
    if not slanted:
        ys = np.full_like(xs, 20)
    depth = np.where(xs < ys, 1.2, 3.0).astype(np.float32)
    edge = xs == ys  # a strip of mixed returns
    mix = rng.uniform(0.1, 0.9, depth.shape)
    depth[edge] = (1.2 * mix + 3.0 * (1 - mix))[edge]
    out = remove_flying_pixels(depth, FOCAL, DepthFilterConfig())
    assert np.count_nonzero(out[edge]) <= 0.05 * edge.sum()
    assert np.all(out[(xs < ys - 2)] == 1.2)


def test_speckles_are_dropped() -> None:
    depth = np.zeros((9, 9), dtype=np.float32)
    depth[4, 4] = 2.0
    assert np.count_nonzero(remove_flying_pixels(depth, FOCAL, DepthFilterConfig())) == 0


def test_bad_input_and_config_are_value_errors() -> None:
    with pytest.raises(ValueError, match="depth_m"):
        filter_depth(np.zeros((2, 2, 2), np.float32), FOCAL, DepthFilterConfig())
    with pytest.raises(ValueError, match="focal_px"):
        filter_depth(np.zeros((2, 2), np.float32), 0.0, DepthFilterConfig())
    with pytest.raises(ValueError):
        DepthFilterConfig(min_depth_m=3.0, max_depth_m=1.0)
