from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from pipeline.reconstruct.meshing import (
    MeshingConfig,
    drop_unsupported_components,
    mesh_cloud,
    poisson_disk_indices,
    poisson_disk_samples,
)
from tests.pipeline.sphere_scene import CENTRE, distance_to_sphere, sphere_cloud


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31), count=st.integers(2, 3000),
       radius=st.floats(0.01, 0.2))
def test_poisson_disk_samples_are_apart_and_cover_the_cloud(seed: int, count: int,
                                                            radius: float) -> None:
    points = np.random.default_rng(seed).uniform(-0.5, 0.5, size=(count, 3))
    idx = poisson_disk_indices(points, radius, seed)
    assert len(np.unique(idx)) == len(idx) > 0
    chosen = points[idx]
    if len(idx) > 1:
        nearest, _ = cKDTree(chosen).query(chosen, k=2)
        assert nearest[:, 1].min() >= radius * (1 - 1e-9)
    # Maximal: every point lies within 2 radii of a sample (one cell plus one disk).
    dist, _ = cKDTree(chosen).query(points)
    assert dist.max() < 2 * radius


def test_averaged_samples_are_less_noisy_than_the_cloud() -> None:
    points, normals = sphere_cloud(60_000, 0.002)
    samples, sample_normals = poisson_disk_samples(points, normals, MeshingConfig())
    assert len(samples) < len(points) / 3
    assert np.std(distance_to_sphere(samples)) < 0.6 * np.std(distance_to_sphere(points))
    np.testing.assert_allclose(np.linalg.norm(sample_normals, axis=1), 1.0, atol=1e-6)


def test_a_noisy_sphere_cloud_becomes_a_close_surface() -> None:
    points, normals = sphere_cloud(60_000, 0.001)
    mesh, samples = mesh_cloud(points, normals, MeshingConfig())
    assert samples > 1000
    d = distance_to_sphere(mesh.vertices_m)
    assert np.sqrt(np.mean(d**2)) < 0.001
    # Outward-facing triangles (counter-clockwise seen from outside).
    tri = mesh.vertices_m[mesh.faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert np.mean(np.sum(n * (tri.mean(axis=1) - CENTRE), axis=1) > 0) > 0.99


def test_the_surface_is_trimmed_where_nothing_was_seen() -> None:
    points, normals = sphere_cloud(60_000, 0.0)
    cap = points[:, 1] > CENTRE[1]  # only the upper half was seen
    mesh, _ = mesh_cloud(points[cap], normals[cap], MeshingConfig())
    assert mesh.vertices_m[:, 1].min() > CENTRE[1] - 0.03


def test_the_same_cloud_meshes_to_the_same_surface() -> None:
    """One Poisson thread (the default): with two, runs on this cloud give different vertex
    arrays."""
    points, normals = sphere_cloud(60_000, 0.002)
    first, _ = mesh_cloud(points, normals, MeshingConfig())
    again, _ = mesh_cloud(points, normals, MeshingConfig())
    assert np.array_equal(first.faces, again.faces)
    assert np.array_equal(first.vertices_m, again.vertices_m)


@pytest.mark.parametrize("field", ["threads", "poisson_threads"])
def test_a_thread_count_of_zero_is_named(field: str) -> None:
    with pytest.raises(ValueError, match="threads"):
        MeshingConfig(**{field: 0})


def test_too_few_points_is_a_value_error() -> None:
    with pytest.raises(ValueError, match="points_world"):
        mesh_cloud(np.zeros((2, 3)), np.zeros((2, 3), np.float32), MeshingConfig())


def _square(centre: np.ndarray, side_m: float, step_m: float) -> np.ndarray:
    ticks = np.arange(-side_m / 2, side_m / 2 + 1e-9, step_m)
    xs, ys = np.meshgrid(ticks, ticks)
    return centre + np.column_stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)])


def test_small_seen_pieces_of_a_scene_stay() -> None:
    """A wall and a few small separate things before it, each truly seen (a share of the
    largest piece would drop them)."""
    wall = _square(np.zeros(3), 1.0, 0.003)
    things = [_square(np.array([x, 0.3, 0.3]), 0.04, 0.003) for x in (-0.3, 0.0, 0.3)]
    points = np.vstack([wall, *things])
    normals = np.tile(np.array([0, 0, 1], np.float32), (len(points), 1))
    mesh, _ = mesh_cloud(points, normals, MeshingConfig())
    near_thing = [np.linalg.norm(mesh.vertices_m - t.mean(axis=0), axis=1).min() for t in things]
    assert max(near_thing) < 0.005
    assert np.abs(mesh.vertices_m[:, 2]).max() < 0.31


def test_pieces_almost_no_sample_lies_on_are_dropped() -> None:
    vertices = np.array([[0, 0, 0], [0.01, 0, 0], [0, 0.01, 0],
                         [1, 0, 0], [1.01, 0, 0], [1, 0.01, 0]], dtype=np.float64)
    faces = np.array([[0, 1, 2], [3, 4, 5]], dtype=np.int32)
    samples = np.vstack([np.tile([0.003, 0.003, 0.0], (5, 1)), [[1.003, 0.003, 0.0]]])
    kept_v, kept_f = drop_unsupported_components(vertices, faces, samples, 0.012,
                                                 MeshingConfig(min_component_samples=3))
    assert len(kept_f) == 1 and kept_v[:, 0].max() < 0.5
