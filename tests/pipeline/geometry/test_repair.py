from __future__ import annotations

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.geometry.mesh import FACE_BLOCK_FACES
from pipeline.geometry.repair import (
    _first_of_each_corner_set,
    drop_small_components,
    edge_table,
    face_areas,
    faces_at,
    faces_per_edge,
    grown_by_rings,
    non_manifold_vertices,
    repair,
    stable_sort,
    triangle_angles_deg,
    without_rows,
)


def _box() -> tuple[np.ndarray, np.ndarray]:
    box = trimesh.creation.box()
    return np.asarray(box.vertices, dtype=float), np.asarray(box.faces, dtype=np.int32)


def test_edge_table_lists_each_edge_once_and_opposite_corners() -> None:
    v, f = _box()
    edges, opposite = edge_table(f)
    assert len(edges) == 18  # 12 box edges + 6 face diagonals
    assert np.all(np.bincount(opposite.ravel()) == 2)
    for face, row in zip(f, opposite, strict=True):
        for corner in range(3):
            pair = sorted((face[(corner + 1) % 3], face[(corner + 2) % 3]))
            assert list(edges[row[corner]]) == pair


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), vertex_count=st.integers(3, 30),
       face_count=st.integers(0, 60))
def test_edge_table_sorts_edges_and_names_each_corners_opposite_edge(
        seed: int, vertex_count: int, face_count: int) -> None:
    faces = np.random.default_rng(seed).integers(0, vertex_count, (face_count, 3)).astype(np.int32)
    edges, opposite = edge_table(faces)
    expected = sorted({tuple(sorted((int(f[(c + 1) % 3]), int(f[(c + 2) % 3]))))
                       for f in faces for c in range(3)})
    assert edges.tolist() == [list(e) for e in expected]
    for f, row in zip(faces, opposite, strict=True):
        for c in range(3):
            assert set(edges[row[c]].tolist()) == {f[(c + 1) % 3], f[(c + 2) % 3]}


def test_angles_of_a_right_triangle() -> None:
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=float)
    np.testing.assert_allclose(triangle_angles_deg(v, np.array([[0, 1, 2]], np.int32)),
                               [[90, 45, 45]])


def test_repair_removes_degenerate_duplicate_and_non_manifold_faces() -> None:
    v, f = _box()
    v = np.vstack([v, [[0, 0, 2], [5, 5, 5]]])
    fin = [[0, 1, 8]]  # a third face on the box edge (0, 1)
    faces = np.vstack([f, f[:2], [[2, 2, 3]], fin]).astype(np.int32)
    out_v, out_f, removed = repair(v, faces)
    assert removed["duplicate"] == 2 and removed["degenerate"] == 1
    assert removed["non_manifold"] >= 3
    _, opposite = edge_table(out_f)
    assert np.bincount(opposite.ravel()).max() <= 2
    assert not non_manifold_vertices(out_f, len(out_v)).any()
    assert len(out_v) == len(np.unique(out_f))  # unreferenced vertices dropped


def test_bow_tie_vertices_are_found() -> None:
    f = np.array([[0, 1, 2], [0, 3, 4]], dtype=np.int32)
    assert non_manifold_vertices(f, 5).tolist() == [True, False, False, False, False]


def test_small_pieces_are_dropped() -> None:
    v, f = _box()
    big = trimesh.creation.icosphere(subdivisions=2)
    verts = np.vstack([np.asarray(big.vertices), v + 5])
    faces = np.vstack([np.asarray(big.faces), f + len(big.vertices)]).astype(np.int32)
    out_v, out_f = drop_small_components(verts, faces, 0.1)
    assert len(out_f) == len(big.faces) and len(out_v) == len(big.vertices)


def test_bad_arrays_are_value_errors() -> None:
    v, f = _box()
    with pytest.raises(ValueError, match="faces"):
        repair(v, f + 100)
    with pytest.raises(ValueError, match="vertices_m"):
        repair(np.full_like(v, np.nan), f)


def test_faces_per_edge_tells_boundary_interior_and_non_manifold_edges():
    closed = np.array([[0, 1, 2], [0, 3, 1], [1, 3, 2], [2, 3, 0]], dtype=np.int32)
    edges, opposite = edge_table(closed)
    assert (faces_per_edge(opposite, len(edges)) == 2).all()
    edges, opposite = edge_table(closed[:1])
    assert (faces_per_edge(opposite, len(edges)) == 1).all()
    # Three triangles on the edge (0, 1): it is used three times, every other edge once.
    fan = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]], dtype=np.int32)
    edges, opposite = edge_table(fan)
    uses = faces_per_edge(opposite, len(edges))
    assert uses[np.flatnonzero((edges == [0, 1]).all(axis=1))[0]] == 3
    assert sorted(uses) == [1] * 6 + [3]


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), faces=st.integers(1, 200), vertices=st.integers(3, 12))
def test_duplicates_are_found_whatever_the_corners_order(seed: int, faces: int,
                                                         vertices: int) -> None:
    """The first face of each set with the same corners, as np.unique over sorted rows finds
    it: few vertices, so many faces repeat, with their corners turned or flipped."""
    f = np.random.default_rng(seed).integers(0, vertices, (faces, 3))
    _, expected = np.unique(np.sort(f, axis=1), axis=0, return_index=True)
    assert np.array_equal(_first_of_each_corner_set(f), np.sort(expected))


@settings(max_examples=60, deadline=None)
@given(keys=st.lists(st.integers(0, 2**62), max_size=300), span=st.sampled_from([3, 1000, 0]))
def test_stable_sort_is_numpys_stable_argsort(keys: list[int], span: int) -> None:
    """Small keys (many ties) take the packed sort, keys too wide to pack beside their index
    the stable argsort: both give the stable order and the sorted keys."""
    values = np.array(keys, dtype=np.int64) % span if span else np.array(keys, dtype=np.int64)
    sorted_keys, order = stable_sort(values)
    expected = np.argsort(values, kind="stable")
    assert np.array_equal(order, expected)
    assert np.array_equal(sorted_keys, values[expected])


@pytest.mark.parametrize("faces", [0, 100, 2 * FACE_BLOCK_FACES + 37])
def test_face_areas_are_half_the_cross_products_norm(faces: int) -> None:
    """The same bits by blocks of faces as numpy's cross product and norm on the whole."""
    rng = np.random.default_rng(3)
    v = rng.normal(size=(40, 3))
    f = rng.integers(0, 40, (faces, 3)).astype(np.int32)
    tri = v[f]
    expected = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    assert np.array_equal(face_areas(v, f), expected)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), vertices=st.integers(3, 40),
       faces=st.sampled_from([0, 1, 200, FACE_BLOCK_FACES, 2 * FACE_BLOCK_FACES + 37]))
def test_triangle_angles_are_the_gathered_corners_angles(seed: int, vertices: int,
                                                         faces: int) -> None:
    """The columns' form, by blocks of faces, gives the bits of the plain form on gathered
    corners, degenerate faces (a repeated corner: 0 for each angle at a zero-length side)
    included."""
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(vertices, 3))
    f = rng.integers(0, vertices, (faces, 3)).astype(np.int32)
    tri = v[f]
    side = [tri[:, (c + 1) % 3] - tri[:, c] for c in range(3)]
    length = [np.linalg.norm(s, axis=1) for s in side]
    expected = np.zeros(f.shape)
    for c in range(3):
        denom = length[c] * length[c - 1]
        cos = np.divide(-np.sum(side[c] * side[c - 1], axis=1), denom, out=np.ones(len(f)),
                        where=denom > 0)
        expected[:, c] = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    assert np.array_equal(triangle_angles_deg(v, f), expected)
    whole = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])
    np.testing.assert_allclose(expected[whole].sum(axis=1), 180.0, atol=1e-4)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), rings=st.integers(0, 4), share=st.floats(0.0, 0.05))
def test_growing_by_rings_adds_each_rings_faces_corners(seed: int, rings: int,
                                                        share: float) -> None:
    sphere = trimesh.creation.icosphere(subdivisions=3)
    faces = np.asarray(sphere.faces, dtype=np.int32)
    rng = np.random.default_rng(seed)
    seeds = rng.uniform(size=len(sphere.vertices)) < share
    near, at_near = grown_by_rings(faces, seeds, rings)
    expected = seeds.copy()
    for _ in range(rings):  # a ring: every corner of every face that touches the set
        expected[faces[expected[faces].any(axis=1)].ravel()] = True
    assert np.array_equal(near, expected)
    assert np.array_equal(at_near, faces_at(faces, expected))
    assert not np.shares_memory(near, seeds) and np.array_equal(seeds[seeds], near[seeds])


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), rows=st.integers(0, 700),
       share=st.sampled_from([0.0, 0.01, 0.5, 1.0]))
def test_without_rows_is_a_mask_of_the_rows_kept(seed: int, rows: int, share: float) -> None:
    """Runs copied (few rows dropped) or a mask (more than `RUN_COPY_MAX_DROPPED`): the rows
    kept, in order."""
    rng = np.random.default_rng(seed)
    array = rng.normal(size=(rows, 3))
    dropped = np.flatnonzero(rng.random(rows) < share)
    keep = np.ones(rows, dtype=bool)
    keep[dropped] = False
    assert np.array_equal(without_rows(array, dropped), array[keep])
