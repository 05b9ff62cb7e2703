from __future__ import annotations

import numpy as np
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.geometry.mesh import (
    FACE_BLOCK_FACES,
    TriangleMesh,
    face_cross_m2,
    face_normals,
    mean_edge_length_m,
    vertex_normals,
)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), vertices=st.integers(3, 30),
       faces=st.sampled_from([0, 100, FACE_BLOCK_FACES, 2 * FACE_BLOCK_FACES + 37]))
def test_face_cross_is_numpys_cross_of_the_gathered_corners(seed: int, vertices: int,
                                                            faces: int) -> None:
    """By blocks of faces, the same bits as numpy's cross product on the whole."""
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(vertices, 3))
    f = rng.integers(0, vertices, (faces, 3)).astype(np.int32)
    tri = v[f]
    assert np.array_equal(face_cross_m2(v, f),
                          np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]))


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), vertices=st.integers(3, 30))
def test_mean_edge_length_is_numpys_norm_of_the_gathered_ends(seed: int, vertices: int) -> None:
    """Coordinate by coordinate, the same bits as the mean of np.linalg.norm over each face's
    three edges in turn."""
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(vertices, 3)) * 10.0 ** rng.uniform(-3, 1)
    f = rng.integers(0, vertices, (100, 3)).astype(np.int32)
    ends = [(v[f[:, c]], v[f[:, (c + 1) % 3]]) for c in range(3)]
    expected = np.concatenate([np.linalg.norm(a - b, axis=1) for a, b in ends]).mean()
    assert mean_edge_length_m(TriangleMesh(vertices_m=v, faces=f)) == float(expected)


def test_normals_of_a_sphere_point_out_and_a_degenerate_face_has_none() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    v = np.asarray(sphere.vertices, np.float64)
    f = np.asarray(sphere.faces, np.int32)
    outward = v / np.linalg.norm(v, axis=1, keepdims=True)
    assert np.all(np.sum(vertex_normals(v, f) * outward, axis=1) > 0.999)
    centroids = v[f].mean(axis=1)
    assert np.all(np.sum(face_normals(v, f) * centroids, axis=1) > 0)
    flat = np.array([[0, 1, 1]], dtype=np.int32)
    assert np.array_equal(face_normals(v, flat), np.zeros((1, 3)))
