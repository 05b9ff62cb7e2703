"""The speculative remesh: started on a mesh whose vertices move before it ends."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.geometry.mesh import TriangleMesh, mean_edge_length_m
from pipeline.reconstruct.remesh.isotropic import RemeshConfig, remesh
from pipeline.reconstruct.remesh.kernel import located_on
from pipeline.reconstruct.remesh.speculative import (
    checked_faces,
    finish_remesh_ahead,
    in_background,
    midpoints_extended,
    start_remesh_ahead,
)
from tests.pipeline.reconstruct.remesh.test_pieces import _noisy_sphere


def _config(mesh: TriangleMesh, pieces: int) -> RemeshConfig:
    return RemeshConfig(target_edge_length_m=mean_edge_length_m(mesh), iterations=1,
                        max_kernel_added_outside=2e-4, max_kernel_lost_edges=2.0,
                        min_component_share=0.0, kernel_processes=pieces)


def _distance_to_surface_m(points_m: np.ndarray, mesh: TriangleMesh) -> np.ndarray:
    from gpytoolbox_bindings import _point_mesh_squared_distance_cpp_impl

    squared = _point_mesh_squared_distance_cpp_impl(mesh.vertices_m, mesh.faces, points_m)[0]
    return np.sqrt(np.asarray(squared).ravel())


@pytest.mark.parametrize("pieces", [1, 2])
@pytest.mark.parametrize("open_cap", [False, True])
def test_with_no_move_it_is_the_plain_remesh(pieces: int, open_cap: bool) -> None:
    """Carried onto the mesh it started on, the kernel's result is its own: the same faces
    as `remesh`, the vertices rebuilt from their faces' corners to rounding."""
    mesh = _noisy_sphere(3, open_cap)
    config = _config(mesh, pieces)
    ahead = start_remesh_ahead(mesh, config)
    assert ahead is not None
    carried, stats = finish_remesh_ahead(ahead, mesh)
    plain, plain_stats = remesh(mesh, config)
    assert stats["warning"] is None and stats["kernel_kept"] and plain_stats["kernel_kept"]
    np.testing.assert_array_equal(carried.faces, plain.faces)
    np.testing.assert_allclose(carried.vertices_m, plain.vertices_m, atol=1e-12)
    assert stats["kernel_lost_edges"] == pytest.approx(plain_stats["kernel_lost_edges"])


@pytest.mark.parametrize("open_cap", [False, True])
def test_the_result_lies_on_the_moved_surface(open_cap: bool) -> None:
    """Moved by a smooth field (a bulge along z and a twist), the carried vertices lie on
    the moved mesh's faces, and the held boundary is the moved boundary."""
    mesh = _noisy_sphere(4, open_cap)
    v = mesh.vertices_m
    angle = 0.3 * v[:, 2]
    moved_m = np.column_stack([v[:, 0] * np.cos(angle) - v[:, 1] * np.sin(angle),
                               v[:, 0] * np.sin(angle) + v[:, 1] * np.cos(angle),
                               v[:, 2] * (1.0 + 0.05 * v[:, 2])])
    moved = TriangleMesh(vertices_m=moved_m, faces=mesh.faces)
    ahead = start_remesh_ahead(mesh, _config(mesh, 2))
    assert ahead is not None
    out, stats = finish_remesh_ahead(ahead, moved)
    assert stats["warning"] is None and stats["kernel_kept"]
    # The angle clean-up's collapses move a few vertices to edge midpoints, on the surface.
    assert _distance_to_surface_m(out.vertices_m, moved).max() < 1e-9
    assert out.face_count == pytest.approx(mesh.face_count, rel=0.1)
    unmoved, _ = finish_remesh_ahead(start_remesh_ahead(mesh, _config(mesh, 2)), mesh)
    assert np.abs(out.vertices_m - unmoved.vertices_m).max() > 1e-3  # it did move


def test_a_kernel_it_drops_leaves_the_moved_mesh_cleaned_up() -> None:
    """One round asked for edges far shorter than the mesh's cuts its surface away: dropped,
    and the answer is the moved mesh's clean-up."""
    mesh = _noisy_sphere(5, False, subdivisions=2)
    config = replace(_config(mesh, 1), target_edge_length_m=mean_edge_length_m(mesh) / 10)
    moved = TriangleMesh(vertices_m=mesh.vertices_m * 1.01, faces=mesh.faces)
    ahead = start_remesh_ahead(mesh, config)
    assert ahead is not None
    out, stats = finish_remesh_ahead(ahead, moved)
    assert stats["kernel_kept"] is False
    expected, _ = remesh(moved, replace(config, iterations=0))
    np.testing.assert_array_equal(out.faces, expected.faces)
    np.testing.assert_array_equal(out.vertices_m, expected.vertices_m)


@pytest.mark.parametrize("pieces", [1, 2])
def test_a_kernel_that_fails_leaves_the_moved_mesh_cleaned_up(pieces: int) -> None:
    """A kernel past its timeout, waited for in the join's thread, is a warning, and the
    answer is the moved mesh's clean-up, as for a kernel dropped."""
    mesh = _noisy_sphere(5, False, subdivisions=2)
    config = replace(_config(mesh, pieces), timeout_s=1e-3)
    moved = TriangleMesh(vertices_m=mesh.vertices_m * 1.01, faces=mesh.faces)
    ahead = start_remesh_ahead(mesh, config)
    assert ahead is not None
    out, stats = finish_remesh_ahead(ahead, moved)
    assert "timed out" in stats["warning"] and "kept the unremeshed mesh" in stats["warning"]
    expected, _ = remesh(moved, replace(config, iterations=0))
    np.testing.assert_array_equal(out.faces, expected.faces)
    np.testing.assert_array_equal(out.vertices_m, expected.vertices_m)


def test_a_repair_that_drops_vertices_is_left_to_the_plain_remesh() -> None:
    mesh = _noisy_sphere(6, False, subdivisions=2)
    loose = TriangleMesh(vertices_m=np.vstack([mesh.vertices_m, [[5.0, 5.0, 5.0]]]),
                         faces=mesh.faces)
    assert start_remesh_ahead(loose, _config(loose, 1)) is None


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**16), count=st.integers(0, 40))
def test_midpoints_are_built_in_their_order(seed: int, count: int) -> None:
    rng = np.random.default_rng(seed)
    vertices_m = rng.normal(size=(5, 3))
    parents = np.array([rng.choice(5 + k, 2, replace=False) for k in range(count)],
                       dtype=np.int64).reshape(-1, 2)
    expected = list(vertices_m)
    for a, b in parents:
        expected.append(np.mean([expected[a], expected[b]], axis=0))
    np.testing.assert_array_equal(midpoints_extended(vertices_m, parents), np.array(expected))


def test_points_on_a_mesh_are_located_on_its_faces() -> None:
    mesh = _noisy_sphere(7, False, subdivisions=2)
    rng = np.random.default_rng(0)
    face = rng.integers(0, mesh.face_count, 200)
    weights = rng.dirichlet([1.0, 1.0, 1.0], 200)
    points_m = np.einsum("pk,pkd->pd", weights, mesh.vertices_m[mesh.faces[face]])
    held = np.array([3, 8], dtype=np.int64)
    points_m[:2] = mesh.vertices_m[held]
    ids, found = located_on(mesh.vertices_m, mesh.faces, points_m, held)
    rebuilt_m = np.einsum("pk,pkd->pd", found, mesh.vertices_m[ids])
    np.testing.assert_allclose(rebuilt_m, points_m, atol=1e-12)
    assert ids[:2].tolist() == [[3, 3, 3], [8, 8, 8]] and found[:2, 0].tolist() == [1.0, 1.0]


def test_faces_checked_beforehand_give_the_same_remesh() -> None:
    """`checked_faces` says the faces need nothing and hands over their edge table; started
    with them, the remesh is the one that repairs and builds the table itself. A face the move
    made degenerate is still found and removed."""
    from pipeline.geometry.repair import is_repaired

    mesh = _noisy_sphere(8, True)
    checked = checked_faces(mesh)
    assert checked.repaired and len(checked.opposite) == mesh.face_count
    config = _config(mesh, 2)
    known, known_stats = finish_remesh_ahead(start_remesh_ahead(mesh, config, (), checked), mesh)
    checked_here, _ = finish_remesh_ahead(start_remesh_ahead(mesh, config), mesh)
    np.testing.assert_array_equal(known.faces, checked_here.faces)
    np.testing.assert_array_equal(known.vertices_m, checked_here.vertices_m)
    flat_m = mesh.vertices_m.copy()
    a, b, c = mesh.faces[0]
    flat_m[c] = (flat_m[a] + flat_m[b]) / 2  # face 0 loses its area
    flat = TriangleMesh(vertices_m=flat_m, faces=mesh.faces)
    _, flat_stats = finish_remesh_ahead(start_remesh_ahead(flat, config, (), checked), flat)
    assert flat_stats["repair_removed_faces"]["degenerate"] >= 1
    assert known_stats["repair_removed_faces"]["degenerate"] == 0
    duplicated = np.vstack([mesh.faces, mesh.faces[:1]])
    assert not is_repaired(mesh.vertices_m, duplicated)
    assert not checked_faces(TriangleMesh(vertices_m=mesh.vertices_m, faces=duplicated)).repaired


def test_the_pieces_are_joined_in_a_thread_of_their_own() -> None:
    """The kernel's outcome is waited for and joined beside the caller's work, which it gets
    when it asks; an error raised there is raised to it."""
    import threading

    ran_in, started, release = [], threading.Event(), threading.Event()

    def join() -> tuple[None, str]:
        ran_in.append(threading.current_thread())
        started.set()
        release.wait(5.0)
        return None, "joined"

    wait = in_background(join)
    assert started.wait(5.0)  # started before anyone waits for it
    assert ran_in[0] is not threading.current_thread()
    release.set()
    assert wait() == (None, "joined")

    def failing() -> tuple[None, str]:
        raise ValueError("remesh piece 0: the kernel moved a vertex of its cut")

    with pytest.raises(ValueError, match="moved a vertex"):
        in_background(failing)()
