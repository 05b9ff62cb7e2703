from __future__ import annotations

import numpy as np
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.geometry.repair import edge_table, face_areas, triangle_angles_deg
from pipeline.geometry.subdivide import split_edges


def _sphere() -> tuple[np.ndarray, np.ndarray]:
    sphere = trimesh.creation.icosphere(subdivisions=2)
    return np.asarray(sphere.vertices, dtype=float), np.asarray(sphere.faces, dtype=np.int32)


def _split_at_midpoints(vertices: np.ndarray, faces: np.ndarray, seed: int, share: float
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    edges, _ = edge_table(faces)
    split = np.random.default_rng(seed).random(len(edges)) < share
    out_v, out_f = split_edges(vertices, faces, split, vertices[edges].mean(axis=1))
    return out_v, out_f, split


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), share=st.floats(0.0, 1.0))
def test_splits_at_midpoints_keep_the_surface_closed_oriented_and_the_same(
        seed: int, share: float) -> None:
    vertices, faces = _sphere()
    out_v, out_f, split = _split_at_midpoints(vertices, faces, seed, share)
    assert len(out_v) == len(vertices) + split.sum()
    # A face with k of its edges split becomes k + 1 faces; each edge has two faces.
    assert len(out_f) == len(faces) + 2 * split.sum()
    assert np.isclose(face_areas(out_v, out_f).sum(), face_areas(vertices, faces).sum())
    assert (face_areas(out_v, out_f) > 0).all()
    result = trimesh.Trimesh(out_v, out_f, process=False)
    assert result.is_watertight and result.is_winding_consistent
    assert result.euler_number == 2
    assert np.isclose(result.volume, trimesh.Trimesh(vertices, faces, process=False).volume)


def test_every_edge_split_is_the_four_way_subdivision() -> None:
    vertices, faces = _sphere()
    out_v, out_f, _ = _split_at_midpoints(vertices, faces, 0, 1.0)
    assert len(out_f) == 4 * len(faces)
    # Four blocks of children in the faces' order, each similar to its parent.
    parent = np.sort(triangle_angles_deg(vertices, faces), axis=1)
    children = np.sort(triangle_angles_deg(out_v, out_f), axis=1).reshape(4, len(faces), 3)
    assert np.allclose(children, parent[None], atol=1e-6)


def test_a_split_point_off_the_edge_moves_the_surface_there() -> None:
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], dtype=float)
    faces = np.array([[0, 1, 2], [1, 3, 2]], dtype=np.int32)
    edges, _ = edge_table(faces)
    split = (edges == [1, 2]).all(axis=1)
    points = np.zeros((len(edges), 3))
    points[split] = [0.5, 0.5, 0.2]
    out_v, out_f = split_edges(vertices, faces, split, points)
    assert out_v.shape == (5, 3) and out_f.shape == (4, 3)
    assert np.allclose(out_v[4], [0.5, 0.5, 0.2])
    result = trimesh.Trimesh(out_v, out_f, process=False)
    assert result.is_winding_consistent
    assert (result.face_normals[:, 2] > 0).all()


def test_a_boundary_edge_splits_its_one_face() -> None:
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=float)
    faces = np.array([[0, 1, 2]], dtype=np.int32)
    edges, _ = edge_table(faces)
    split = (edges == [0, 1]).all(axis=1)
    out_v, out_f = split_edges(vertices, faces, split, vertices[edges].mean(axis=1))
    assert len(out_f) == 2
    assert np.isclose(face_areas(out_v, out_f).sum(), 0.5)
