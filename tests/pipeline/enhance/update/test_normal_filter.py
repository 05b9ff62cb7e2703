import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.enhance.training.data import noisy_along_normals
from pipeline.enhance.update.normal_filter import (
    NormalFilterConfig,
    face_neighbours,
    filtered_normals,
    fit_to_normals,
    normal_filter,
)
from pipeline.geometry.mesh import TriangleMesh, face_normals, mean_edge_length_m
from pipeline.geometry.repair import face_areas
from pipeline.geometry.smoothing import laplacian_smooth
from tests.pipeline.geometry.test_boundary import grid
from tests.pipeline.meshes import radial_rms_m, sphere


def fold(n: int, angle_deg: float, spacing_m: float = 0.01) -> TriangleMesh:
    """The `grid` bent along its middle row of vertices (x = half its side) so that its two
    halves meet at `angle_deg` of turn: a crease."""
    mesh = grid(n, spacing_m)
    v = mesh.vertices_m.copy()
    middle = (n // 2) * spacing_m
    beyond = v[:, 0] > middle
    turn = np.radians(angle_deg)
    run = v[beyond, 0] - middle
    v[beyond, 0] = middle + run * np.cos(turn)
    v[beyond, 2] = run * np.sin(turn)
    return TriangleMesh(v, mesh.faces)


def distance_to_fold_m(points_m: np.ndarray, n: int, angle_deg: float,
                       spacing_m: float = 0.01) -> np.ndarray:
    """(P,) distance of points to the plane of the fold's half they lie nearer along the
    surface (split by the plane that bisects the fold)."""
    middle = (n // 2) * spacing_m
    turn = np.radians(angle_deg)
    along = np.array([np.cos(turn), 0.0, np.sin(turn)])
    normal_beyond = np.array([-np.sin(turn), 0.0, np.cos(turn)])
    rel = points_m - [middle, 0.0, 0.0]
    beyond = rel @ along > -rel[:, 0]
    return np.where(beyond, np.abs(rel @ normal_beyond), np.abs(rel[:, 2]))


def test_off_leaves_the_mesh_as_it_is(noisy_sphere) -> None:
    _, noisy = noisy_sphere
    assert normal_filter(noisy, NormalFilterConfig(normal_iterations=0)) is noisy


def test_face_neighbours_are_the_faces_sharing_a_vertex_itself_included() -> None:
    mesh = grid(4)
    other, row_starts = face_neighbours(mesh.faces, mesh.vertex_count)
    for f in range(len(mesh.faces)):
        expected = {g for g in range(len(mesh.faces)) if set(mesh.faces[f]) & set(mesh.faces[g])}
        row = other[row_starts[f]:row_starts[f + 1]].tolist()
        assert len(row) == len(expected) and set(row) == expected


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(3, 7), rounds=st.integers(1, 3))
def test_filtered_normals_follow_the_bilateral_average_face_by_face(
    seed: int, n: int, rounds: int
) -> None:
    """The sampled products on the sparse pattern give Zheng et al.'s weighted average,
    written out here one face and one neighbour at a time."""
    mesh = grid(n)
    bumpy = mesh.vertices_m + np.random.default_rng(seed).uniform(
        -0.004, 0.004, mesh.vertices_m.shape)
    config = NormalFilterConfig(normal_iterations=rounds)
    faces = mesh.faces
    normals, areas = face_normals(bumpy, faces), face_areas(bumpy, faces)
    centroids = bumpy[faces].mean(axis=1)
    sigma_m = config.spatial_sigma_edges * mean_edge_length_m(TriangleMesh(bumpy, faces))
    for _ in range(rounds):
        averaged = np.zeros_like(normals)
        for f in range(len(faces)):
            for g in range(len(faces)):
                if set(faces[f]) & set(faces[g]):
                    gap = np.sum((centroids[f] - centroids[g]) ** 2)
                    unlike = np.sum((normals[f] - normals[g]) ** 2)
                    averaged[f] += areas[g] * np.exp(-gap / (2 * sigma_m**2)) * np.exp(
                        -unlike / (2 * config.range_sigma**2)) * normals[g]
        normals = averaged / np.linalg.norm(averaged, axis=1, keepdims=True)
    np.testing.assert_allclose(filtered_normals(bumpy, faces, config), normals, atol=1e-12)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(4, 12))
def test_vertices_fitted_to_normals_move_along_them_only(seed: int, n: int) -> None:
    mesh = grid(n)
    rng = np.random.default_rng(seed)
    bumpy = mesh.vertices_m + rng.uniform(-0.003, 0.003, mesh.vertices_m.shape) * [0, 0, 1]
    up = np.tile([0.0, 0.0, 1.0], (len(mesh.faces), 1))
    fitted = fit_to_normals(bumpy, mesh.faces, up, 30)
    assert np.array_equal(fitted[:, :2], bumpy[:, :2])
    # Fitting to the plane's own normal flattens the bumps.
    assert np.ptp(fitted[:, 2]) < 0.5 * np.ptp(bumpy[:, 2])


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), share=st.floats(0.05, 0.2))
def test_a_noisy_sphere_comes_back_closer_to_the_sphere(seed: int, share: float) -> None:
    # The filter ends the update, so it sees noise of a fraction of an edge (the protocol's
    # bunny after the update: about 0.9 mm on 5 mm edges), on edges short against the radius.
    clean = sphere(0.5, 64)
    noisy = noisy_along_normals(clean, share * mean_edge_length_m(clean),
                                np.random.default_rng(seed))
    before = radial_rms_m(noisy)
    after = radial_rms_m(normal_filter(noisy, NormalFilterConfig()))
    assert after < 0.65 * before


@settings(max_examples=15, deadline=None)
@given(angle=st.floats(35.0, 100.0), seed=st.integers(0, 2**31 - 1))
def test_a_crease_keeps_its_sides_apart(angle: float, seed: int) -> None:
    n = 21
    clean = fold(n, angle)
    rng = np.random.default_rng(seed)
    noisy = noisy_along_normals(clean, 0.0015, rng)
    filtered = normal_filter(noisy, NormalFilterConfig())
    interior = np.all((clean.vertices_m[:, :2] > 0.025) & (clean.vertices_m[:, 1:2] < 0.175),
                      axis=1)
    err_before = distance_to_fold_m(noisy.vertices_m, n, angle)[interior]
    err_after = distance_to_fold_m(filtered.vertices_m, n, angle)[interior]
    assert np.sqrt(np.mean(err_after**2)) < 0.75 * np.sqrt(np.mean(err_before**2))
    # Laplacian smoothing as strong as it takes to reach the same noise on the flat parts
    # rounds the crease; the filter keeps the vertices on the fold line near it.
    line = interior & (np.abs(clean.vertices_m[:, 0] - (n // 2) * 0.01) < 1e-9)
    smoothed = laplacian_smooth(noisy, 10)
    crease_filtered = np.abs(distance_to_fold_m(filtered.vertices_m[line], n, angle)).max()
    crease_smoothed = np.abs(distance_to_fold_m(smoothed.vertices_m[line], n, angle)).max()
    assert crease_filtered < crease_smoothed


def test_bad_settings_are_named() -> None:
    with pytest.raises(ValueError, match="iterations"):
        NormalFilterConfig(normal_iterations=-1)
    with pytest.raises(ValueError, match="range_sigma"):
        NormalFilterConfig(range_sigma=0.0)


@pytest.mark.skipif(not __import__("torch").cuda.is_available(), reason="no CUDA device")
def test_the_filter_on_cuda_gives_the_cpu_result(noisy_sphere) -> None:
    _, noisy = noisy_sphere
    on_cpu = normal_filter(noisy, NormalFilterConfig(), "cpu")
    on_cuda = normal_filter(noisy, NormalFilterConfig(), "cuda")
    np.testing.assert_allclose(on_cuda.vertices_m, on_cpu.vertices_m, atol=1e-9)
