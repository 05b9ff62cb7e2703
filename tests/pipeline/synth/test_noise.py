"""The Azure Kinect noise model: statistics, range, quantisation, dropouts, flying pixels."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from pipeline.capture import Intrinsics
from pipeline.synth.noise import KinectNoiseConfig, apply_kinect_noise, draw_depth_bias_m

INTR = Intrinsics(width=400, height=300, fx=300.0, fy=300.0, cx=199.5, cy=149.5)
FACING = np.broadcast_to(np.array([0.0, 0.0, -1.0], dtype=np.float32), (300, 400, 3))
# Only the random error: no dropouts, no edges, no bias.
PLAIN = KinectNoiseConfig(invalid_fraction=0.0, edge_invalid_fraction=0.0, flying_fraction=0.0,
                          bias_std_m=0.0)


def _plane(depth_m: float) -> np.ndarray:
    return np.full((INTR.height, INTR.width), depth_m, dtype=np.float32)


@pytest.mark.parametrize("depth_m, sigma_m", [(1.0, 0.001), (2.0, 0.002), (3.0, 0.003)])
def test_random_error_has_the_specified_spread(depth_m: float, sigma_m: float) -> None:
    rng = np.random.default_rng(1)
    noisy = apply_kinect_noise(_plane(depth_m), FACING, INTR, PLAIN, rng)
    # The centre of the image, where the ray is almost the optical axis.
    error = noisy[100:200, 150:250].astype(np.float64) - depth_m
    quantised = np.sqrt(sigma_m**2 + 0.001**2 / 12)
    assert error.std() == pytest.approx(quantised, rel=0.2)
    assert abs(error.mean()) < 0.2 * sigma_m
    assert PLAIN.sigma_m(depth_m) == pytest.approx(sigma_m)


def test_without_quantisation_the_spread_is_the_model_along_the_ray() -> None:
    config = replace(PLAIN, quantization_m=0.0)
    noisy = apply_kinect_noise(_plane(2.0), FACING, INTR, config, np.random.default_rng(2))
    u = (np.arange(INTR.width) - INTR.cx) / INTR.fx
    v = (np.arange(INTR.height) - INTR.cy) / INTR.fy
    scale = np.sqrt(1 + u[None, :] ** 2 + v[:, None] ** 2)
    # Error along the ray, normalised by the model's sigma at that ray length.
    normalised = (noisy - 2.0) * scale / config.sigma_m(2.0 * scale)
    assert normalised.std() == pytest.approx(1.0, rel=0.05)


def test_values_are_whole_millimetres_within_range() -> None:
    depth = np.linspace(0.3, 4.2, INTR.width, dtype=np.float32)[None, :].repeat(INTR.height, 0)
    noisy = apply_kinect_noise(depth, FACING, INTR, PLAIN, np.random.default_rng(3))
    valid = noisy > 0
    np.testing.assert_allclose(noisy[valid] * 1000, np.rint(noisy[valid] * 1000), atol=1e-3)
    assert noisy[valid].min() >= 0.5 and noisy[valid].max() <= 3.86
    assert not valid[:, depth[0] < 0.49].any() and not valid[:, depth[0] > 3.87].any()
    assert valid[:, (depth[0] > 0.52) & (depth[0] < 3.84)].all()


def test_camera_bias_shifts_the_mean() -> None:
    config = replace(PLAIN, bias_std_m=0.003)
    biases = [draw_depth_bias_m(config, np.random.default_rng(s)) for s in range(400)]
    assert np.std(biases) == pytest.approx(0.003, rel=0.15)
    noisy = apply_kinect_noise(_plane(1.5), FACING, INTR, config, np.random.default_rng(4),
                               bias_m=0.004)
    assert float(np.mean(noisy[100:200, 150:250]) - 1.5) == pytest.approx(0.004, abs=2e-4)


def test_grazing_surfaces_drop_out() -> None:
    config = replace(PLAIN, invalid_fraction=0.0)
    u, v = np.meshgrid((np.arange(INTR.width) - INTR.cx) / INTR.fx,
                       (np.arange(INTR.height) - INTR.cy) / INTR.fy)
    rays = np.stack([u, v, np.ones_like(u)], axis=-1)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    # A normal perpendicular to each ray: incidence 90 degrees.
    side = np.cross(rays, [0.0, 1.0, 0.0])
    side /= np.linalg.norm(side, axis=-1, keepdims=True)
    rng = np.random.default_rng(5)
    assert (apply_kinect_noise(_plane(1.0), side, INTR, config, rng) == 0).all()
    # At 60 degrees incidence (cos 0.5) everything survives.
    tilted = 0.5 * -rays + np.sqrt(0.75) * side
    assert (apply_kinect_noise(_plane(1.0), tilted, INTR, config, rng) > 0).all()
    # Halfway along the ramp, about half survive.
    cos = (config.grazing_cos_start + config.grazing_cos_full) / 2
    ramp = cos * -rays + np.sqrt(1 - cos**2) * side
    kept = (apply_kinect_noise(_plane(1.0), ramp, INTR, config, rng) > 0).mean()
    assert kept == pytest.approx(0.5, abs=0.03)


def test_random_invalid_pixels() -> None:
    config = replace(PLAIN, invalid_fraction=0.1)
    noisy = apply_kinect_noise(_plane(1.0), FACING, INTR, config, np.random.default_rng(6))
    assert (noisy == 0).mean() == pytest.approx(0.1, abs=0.01)


def test_depth_edges_make_flying_and_missing_pixels() -> None:
    config = replace(PLAIN, edge_invalid_fraction=0.4, flying_fraction=0.4)
    depth = _plane(1.0)
    depth[:, 200:] = 2.0
    noisy = apply_kinect_noise(depth, FACING, INTR, config, np.random.default_rng(7))
    away = np.ones(INTR.width, bool)
    away[199:201] = False
    assert (noisy[:, away] > 0).all()
    assert (np.abs(noisy[:, away] - depth[:, away]) < 0.02).all()
    edge = noisy[:, 199:201]
    assert (edge == 0).mean() == pytest.approx(0.4, abs=0.06)
    between = (edge > 1.02) & (edge < 1.98)
    assert between.mean() == pytest.approx(0.4, abs=0.08)


def test_silhouettes_fly_towards_the_background_only_when_asked() -> None:
    depth = np.zeros((INTR.height, INTR.width), np.float32)
    depth[:, :200] = 1.0
    config = replace(PLAIN, flying_fraction=1.0)
    flying = apply_kinect_noise(depth, FACING, INTR, config, np.random.default_rng(8))
    assert (flying[:, 199:201] > 1.02).mean() > 0.8
    assert (flying[:, 202:] == 0).all()
    alone = replace(config, background_m=None)
    quiet = apply_kinect_noise(depth, FACING, INTR, alone, np.random.default_rng(8))
    assert (np.abs(quiet[:, :200] - 1.0) < 0.01).all() and (quiet[:, 200:] == 0).all()


def test_same_seed_same_reading() -> None:
    depth = _plane(1.2)
    config = KinectNoiseConfig()
    a = apply_kinect_noise(depth, FACING, INTR, config, np.random.default_rng(9))
    b = apply_kinect_noise(depth, FACING, INTR, config, np.random.default_rng(9))
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("field, value", [("invalid_fraction", 1.5), ("sigma_base_m", -1.0),
                                          ("grazing_cos_full", 0.9), ("max_range_m", 0.1)])
def test_bad_config_names_the_field(field: str, value: float) -> None:
    with pytest.raises(ValueError, match=field):
        KinectNoiseConfig(**{field: value})  # type: ignore[arg-type]


def test_wrong_image_size_is_refused() -> None:
    with pytest.raises(ValueError, match="depth_m"):
        apply_kinect_noise(np.zeros((10, 10)), None, INTR, PLAIN, np.random.default_rng(0))
