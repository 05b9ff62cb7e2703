from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.geometry.mesh import TriangleMesh
from pipeline.geometry.repair import edge_table
from pipeline.reconstruct.quality import sample_surface
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
    fitted, split = fit_to_cloud(mesh, points, normals, SurfaceFitConfig())
    assert np.abs(distance_to_sphere(fitted.vertices_m)).max() < 2e-4
    # A chord of length L lies L**2 / 8R inside the sphere at its middle: 0.25 mm, the
    # tolerance, at 24.5 mm. Edges well short of that stay whole, edges well past it split.
    edges, _ = edge_table(mesh.faces)
    length_m = np.linalg.norm(np.diff(fitted.vertices_m[edges], axis=1)[:, 0], axis=1)
    assert (length_m > 0.027).sum() <= split <= (length_m > 0.022).sum()
    assert fitted.face_count == mesh.face_count + 2 * split


def test_the_fit_averages_the_clouds_noise() -> None:
    points, normals = sphere_cloud(200_000, 0.002)
    fitted, _ = fit_to_cloud(_scaled(sphere_mesh(4), 1.01), points, normals,
                             SurfaceFitConfig())
    rms_m = np.sqrt(np.mean(distance_to_sphere(fitted.vertices_m) ** 2))
    assert rms_m < 0.6e-3


def _ripple_cloud(noise_m: float, wavelength_m: float = 0.04
                  ) -> tuple[np.ndarray, np.ndarray, Callable[[np.ndarray], np.ndarray]]:
    """A 2 mm ripple over a 0.2 m square, sampled every 1.5 mm."""
    def height(x: np.ndarray) -> np.ndarray:
        return 0.002 * np.sin(2 * np.pi * x / wavelength_m)

    rng = np.random.default_rng(0)
    x, y = np.meshgrid(np.arange(0, 0.2, 0.0015), np.arange(0, 0.2, 0.0015), indexing="ij")
    z = height(x) + rng.normal(0, noise_m, size=x.shape)
    slope = 0.002 * 2 * np.pi / wavelength_m * np.cos(2 * np.pi * x / wavelength_m)
    normals = np.column_stack([-slope.ravel(), np.zeros(x.size), np.ones(x.size)])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return np.column_stack([x.ravel(), y.ravel(), z.ravel()]), normals, height


def test_detail_that_the_mesh_smoothed_away_comes_back() -> None:
    points, normals, height = _ripple_cloud(0.0005)
    flat = grid(41, 0.005)
    inner = np.all((flat.vertices_m[:, :2] > 0.02) & (flat.vertices_m[:, :2] < 0.18), axis=1)

    def rms_to_truth(mesh: TriangleMesh) -> float:
        v = mesh.vertices_m[:flat.vertex_count][inner]
        return float(np.sqrt(np.mean((v[:, 2] - height(v[:, 0])) ** 2)))

    fitted, _ = fit_to_cloud(flat, points, normals, SurfaceFitConfig())
    assert rms_to_truth(fitted) < 0.2 * rms_to_truth(flat)


def _surface_rms_m(mesh: TriangleMesh, height: Callable[[np.ndarray], np.ndarray]) -> float:
    """RMS height error of the mesh's surface over the square's inner part."""
    samples, _ = sample_surface(mesh, 200_000, seed=1)
    inner = np.all((samples[:, :2] > 0.04) & (samples[:, :2] < 0.16), axis=1)
    return float(np.sqrt(np.mean((samples[inner, 2] - height(samples[inner, 0])) ** 2)))


def test_edges_too_long_for_the_detail_are_split_onto_it() -> None:
    points, normals, height = _ripple_cloud(0.0005, wavelength_m=0.06)
    coarse = grid(17, 0.0125)
    whole, none_split = fit_to_cloud(coarse, points, normals,
                                     SurfaceFitConfig(split_tolerance_m=1.0))
    split, count = fit_to_cloud(coarse, points, normals, SurfaceFitConfig())
    assert none_split == 0 and count > 0
    assert split.face_count > coarse.face_count
    assert _surface_rms_m(split, height) < 0.75 * _surface_rms_m(whole, height)


def test_noise_alone_splits_fewer_edges_than_detail() -> None:
    coarse = grid(17, 0.0125)
    flat, flat_normals, _ = _ripple_cloud(0.0005, wavelength_m=1e9)
    rippled, rippled_normals, _ = _ripple_cloud(0.0005, wavelength_m=0.06)
    _, in_noise = fit_to_cloud(coarse, flat, flat_normals, SurfaceFitConfig())
    _, on_detail = fit_to_cloud(coarse, rippled, rippled_normals, SurfaceFitConfig())
    assert in_noise < 0.3 * on_detail


def test_where_the_noise_hides_the_tolerance_the_significance_test_keeps_edges() -> None:
    coarse = grid(17, 0.0125)
    noisy, normals, _ = _ripple_cloud(0.002, wavelength_m=1e9)
    _, guarded = fit_to_cloud(coarse, noisy, normals, SurfaceFitConfig())
    _, unguarded = fit_to_cloud(coarse, noisy, normals, SurfaceFitConfig(split_significance=0))
    _, stricter = fit_to_cloud(coarse, noisy, normals, SurfaceFitConfig(split_significance=2))
    assert stricter < 0.5 * guarded < 0.4 * unguarded


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
    moved_m = np.abs(fit_to_cloud(top, points, normals, config)[0].vertices_m[:, 2]).max()
    assert (moved_m > 1e-3) == pulled


def test_vertices_with_no_points_nearby_stay() -> None:
    points, normals = sphere_cloud(10_000, 0.0)
    far = TriangleMesh(sphere_mesh(2).vertices_m + [5.0, 0.0, 0.0], sphere_mesh(2).faces)
    np.testing.assert_array_equal(
        fit_to_cloud(far, points, normals, SurfaceFitConfig())[0].vertices_m, far.vertices_m)


@pytest.mark.parametrize("fields", [{"neighbours": 0}, {"max_shift_m": 0.0},
                                    {"min_normal_cosine": 1.5}, {"threads": 0},
                                    {"split_tolerance_m": 0.0}, {"split_significance": -1.0}])
def test_bad_settings_are_named(fields: dict) -> None:
    with pytest.raises(ValueError, match="surface_fit"):
        SurfaceFitConfig(**fields)
