from __future__ import annotations

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.geometry.mesh import TriangleMesh, mean_edge_length_m
from pipeline.geometry.order import reordered, spatial_order
from pipeline.geometry.repair import edge_table, faces_per_edge
from pipeline.reconstruct.remesh.isotropic import RemeshConfig, kernel_piece_count, remesh
from pipeline.reconstruct.remesh.kernel import kernel
from pipeline.reconstruct.remesh.pieces import held_vertices, spatial_pieces, stitched


def _noisy_sphere(seed: int, open_cap: bool, subdivisions: int = 4) -> TriangleMesh:
    """An icosphere of 0.5 m with vertex noise, its faces in a spatial order; cut open at
    the top where `open_cap`."""
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=0.5)
    v = np.asarray(sphere.vertices, np.float64)
    v += np.random.default_rng(seed).normal(scale=0.002, size=v.shape)
    f = np.asarray(sphere.faces, np.int32)
    if open_cap:
        f = f[v[f].mean(axis=1)[:, 2] < 0.3]
        used = np.unique(f)
        v, f = v[used], np.searchsorted(used, f).astype(np.int32)
    mesh = TriangleMesh(vertices_m=v, faces=f)
    return reordered(mesh, spatial_order(mesh))


def _edge_uses(faces: np.ndarray) -> np.ndarray:
    edges, opposite = edge_table(faces)
    return faces_per_edge(opposite, len(edges))


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 2**16), count=st.integers(2, 5), open_cap=st.booleans())
def test_pieces_remeshed_apart_join_into_one_manifold_surface(
    seed: int, count: int, open_cap: bool
) -> None:
    mesh = _noisy_sphere(seed, open_cap)
    edge_m = mean_edge_length_m(mesh)
    pieces = spatial_pieces(mesh.faces, count)
    assert sum(len(p.faces) for p in pieces) == mesh.face_count
    results = [kernel(mesh.vertices_m[p.vertex_ids], p.faces, edge_m, 1) for p in pieces]
    vertices_m, faces, _ = stitched(mesh.vertices_m, pieces, results)
    uses = _edge_uses(faces)
    # No seam opened and none overlaps: the boundary is the input's, every other edge has
    # two faces, and the surface keeps its topology (Euler characteristic).
    assert uses.max() == 2
    assert (uses == 1).sum() == (_edge_uses(mesh.faces) == 1).sum()
    euler_in = mesh.vertex_count - len(_edge_uses(mesh.faces)) + mesh.face_count
    assert len(vertices_m) - len(uses) + len(faces) == euler_in
    assert np.array_equal(np.unique(faces), np.arange(len(vertices_m)))
    # Each cut vertex is kept where it was.
    for piece, (_, _, held) in zip(pieces, results, strict=True):
        assert np.array_equal(held, held_vertices(piece.faces))
        held_m = mesh.vertices_m[piece.vertex_ids[held]]
        assert np.isin(held_m.view("f8,f8,f8"), vertices_m.view("f8,f8,f8")).all()
    # Still the sphere, and about as finely meshed as in one piece.
    radius_m = np.linalg.norm(vertices_m, axis=1)
    assert np.abs(radius_m - 0.5).max() < 0.02
    whole_v, whole_f, _ = kernel(mesh.vertices_m, mesh.faces, edge_m, 1)
    assert len(faces) == pytest.approx(len(whole_f), rel=0.03)


def test_a_piece_that_moved_a_cut_vertex_is_refused() -> None:
    mesh = _noisy_sphere(0, False, subdivisions=3)
    pieces = spatial_pieces(mesh.faces, 2)
    # The pieces as they came, held vertices first but moved: joining them must fail loudly.
    moved = []
    for p in pieces:
        v, held = mesh.vertices_m[p.vertex_ids], held_vertices(p.faces)
        moved.append((v[np.r_[held, np.setdiff1d(np.arange(len(v)), held)]] + 1e-3, p.faces,
                      held))
    with pytest.raises(ValueError, match="piece 0"):
        stitched(mesh.vertices_m, pieces, moved)


def test_held_vertices_are_the_boundary() -> None:
    faces = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int32)
    assert held_vertices(faces).tolist() == [0, 1, 2, 3]
    closed = np.asarray(trimesh.creation.icosphere(subdivisions=1).faces, np.int32)
    assert len(held_vertices(closed)) == 0


def test_the_piece_count_follows_the_cores_and_the_mesh_size() -> None:
    import os

    from pipeline.reconstruct.remesh.isotropic import MIN_PIECE_FACES

    cores = len(os.sched_getaffinity(0))
    assert kernel_piece_count(10, None) == 1
    assert kernel_piece_count(100 * MIN_PIECE_FACES, None) == cores
    assert kernel_piece_count(3 * MIN_PIECE_FACES, None) == min(cores, 3)
    assert kernel_piece_count(10, 4) == 4 and kernel_piece_count(3, 8) == 3
    with pytest.raises(ValueError, match="kernel_processes"):
        RemeshConfig(kernel_processes=0)


@pytest.mark.parametrize("open_cap", [False, True])
def test_remesh_in_child_pieces_matches_one_child(open_cap: bool) -> None:
    """Through `remesh`, three children: a closed manifold where the input was, the same
    angle criteria met, nearly the same faces as the whole mesh in one child."""
    mesh = _noisy_sphere(1, open_cap)
    config = RemeshConfig(target_edge_length_m=mean_edge_length_m(mesh), iterations=1,
                          min_component_share=0.0)
    one, one_stats = remesh(mesh, config)
    three, three_stats = remesh(mesh, RemeshConfig(**{**config.__dict__,
                                                      "kernel_processes": 3}))
    assert one_stats["warning"] is None and three_stats["warning"] is None
    uses = _edge_uses(three.faces)
    assert uses.max() == 2 and ((uses == 1).sum() > 0) == open_cap
    assert three_stats["angles"]["share_below_min"] <= 0.002
    assert three.face_count == pytest.approx(one.face_count, rel=0.03)
    assert np.abs(np.linalg.norm(three.vertices_m, axis=1) - 0.5).max() < 0.02
