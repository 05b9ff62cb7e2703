from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.geometry.mesh import TriangleMesh
from pipeline.reconstruct.surface_fit import SurfaceFitConfig, fit_to_cloud
from tests.pipeline.meshes import grid
from tests.pipeline.sphere_scene import (
    CENTRE,
    RADIUS,
    distance_to_sphere,
    sphere_cloud,
    sphere_mesh,
)


def _scaled(mesh: TriangleMesh, factor: float) -> TriangleMesh:
    return TriangleMesh(CENTRE + (mesh.vertices_m - CENTRE) * factor, mesh.faces)


@settings(max_examples=15, deadline=None)
@given(offset_m=st.floats(-0.008, 0.008), seed=st.integers(0, 2**31))
def test_an_offset_sphere_comes_back_onto_its_cloud(offset_m: float, seed: int) -> None:
    points, normals = sphere_cloud(200_000, 0.0, seed)
    mesh = _scaled(sphere_mesh(4), 1 + offset_m / RADIUS)
    fitted = fit_to_cloud(mesh, points, normals, SurfaceFitConfig())
    assert np.abs(distance_to_sphere(fitted.vertices_m)).max() < 2e-4
    np.testing.assert_array_equal(fitted.faces, mesh.faces)


def test_the_fit_averages_the_clouds_noise() -> None:
    points, normals = sphere_cloud(200_000, 0.002)
    fitted = fit_to_cloud(_scaled(sphere_mesh(4), 1.01), points, normals, SurfaceFitConfig())
    rms_m = np.sqrt(np.mean(distance_to_sphere(fitted.vertices_m) ** 2))
    assert rms_m < 0.6e-3


def _ripple_cloud(noise_m: float) -> tuple[np.ndarray, np.ndarray, object]:
    """A 2 mm ripple of 4 cm wavelength over a 0.2 m square, sampled every 1.5 mm."""
    def height(x: np.ndarray) -> np.ndarray:
        return 0.002 * np.sin(2 * np.pi * x / 0.04)

    rng = np.random.default_rng(0)
    x, y = np.meshgrid(np.arange(0, 0.2, 0.0015), np.arange(0, 0.2, 0.0015), indexing="ij")
    z = height(x) + rng.normal(0, noise_m, size=x.shape)
    slope = 0.002 * 2 * np.pi / 0.04 * np.cos(2 * np.pi * x / 0.04)
    normals = np.column_stack([-slope.ravel(), np.zeros(x.size), np.ones(x.size)])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return np.column_stack([x.ravel(), y.ravel(), z.ravel()]), normals, height


def test_detail_that_the_mesh_smoothed_away_comes_back() -> None:
    points, normals, height = _ripple_cloud(0.0005)
    flat = grid(41, 0.005)
    inner = np.all((flat.vertices_m[:, :2] > 0.02) & (flat.vertices_m[:, :2] < 0.18), axis=1)

    def rms_to_truth(mesh: TriangleMesh) -> float:
        v = mesh.vertices_m[inner]
        return float(np.sqrt(np.mean((v[:, 2] - height(v[:, 0])) ** 2)))

    fitted = fit_to_cloud(flat, points, normals, SurfaceFitConfig())
    assert rms_to_truth(fitted) < 0.2 * rms_to_truth(flat)


@pytest.mark.parametrize("min_normal_cosine, pulled", [(0.5, False), (-1.0, True)])
def test_the_far_side_of_a_thin_part_does_not_pull(min_normal_cosine: float,
                                                    pulled: bool) -> None:
    top = grid(21, 0.005)
    x, y = np.meshgrid(np.arange(0, 0.1, 0.001), np.arange(0, 0.1, 0.001), indexing="ij")
    sheet = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    points = np.concatenate([sheet, sheet - [0, 0, 0.004]])
    normals = np.concatenate([np.tile([0.0, 0.0, 1.0], (len(sheet), 1)),
                              np.tile([0.0, 0.0, -1.0], (len(sheet), 1))])
    config = SurfaceFitConfig(neighbours=64, min_normal_cosine=min_normal_cosine)
    moved_m = np.abs(fit_to_cloud(top, points, normals, config).vertices_m[:, 2]).max()
    assert (moved_m > 1e-3) == pulled


def test_vertices_with_no_points_nearby_stay() -> None:
    points, normals = sphere_cloud(10_000, 0.0)
    far = TriangleMesh(sphere_mesh(2).vertices_m + [5.0, 0.0, 0.0], sphere_mesh(2).faces)
    np.testing.assert_array_equal(
        fit_to_cloud(far, points, normals, SurfaceFitConfig()).vertices_m, far.vertices_m)


@pytest.mark.parametrize("fields", [{"neighbours": 0}, {"max_shift_m": 0.0},
                                    {"min_normal_cosine": 1.5}, {"threads": 0}])
def test_bad_settings_are_named(fields: dict) -> None:
    with pytest.raises(ValueError, match="surface_fit"):
        SurfaceFitConfig(**fields)
