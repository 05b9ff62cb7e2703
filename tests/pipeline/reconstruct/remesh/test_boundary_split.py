from __future__ import annotations

import numpy as np
import pytest
import trimesh
from hypothesis import example, given, settings
from hypothesis import strategies as st

from pipeline.geometry.repair import edge_table, face_areas, faces_per_edge
from pipeline.reconstruct.remesh.boundary_split import (
    split_boundary_edges,
    split_boundary_edges_with_parents,
    split_everywhere,
)


@settings(max_examples=25, deadline=None)
@given(cut=st.floats(0.05, 0.9), target_m=st.floats(0.01, 0.2), seed=st.integers(0, 2**16))
@example(cut=0.05, target_m=0.05, seed=29)  # no face cut away: a closed mesh, left alone
def test_long_edges_at_the_boundary_are_split_and_the_surface_kept(
    cut: float, target_m: float, seed: int,
) -> None:
    """A coarse sphere cut open (a few long boundary edges and their fans): afterwards no
    edge with an end on the boundary is longer than 4/3 of the target, the faces cover the
    same surface with the same orientation, and the mesh stays manifold. A small cut may
    leave the sphere closed: then there is nothing to split."""
    sphere = trimesh.creation.icosphere(subdivisions=1, radius=0.5)
    v = np.asarray(sphere.vertices) * (1 + 0.05 * np.random.default_rng(seed).random((42, 1)))
    f = np.asarray(sphere.faces, np.int32)
    f = f[v[f].mean(axis=1)[:, 2] < 0.5 - cut]
    out_v, out_f = split_boundary_edges(v, f, target_m)
    edges, opposite = edge_table(out_f)
    uses = faces_per_edge(opposite, len(edges))
    assert uses.max() <= 2
    boundary = np.zeros(len(out_v), dtype=bool)
    boundary[edges[uses == 1].ravel()] = True
    length_m = np.linalg.norm(out_v[edges[:, 0]] - out_v[edges[:, 1]], axis=1)
    assert length_m[boundary[edges].any(axis=1)].max(initial=0.0) <= target_m * 4 / 3 + 1e-12
    assert face_areas(out_v, out_f).sum() == pytest.approx(face_areas(v, f).sum(), rel=1e-9)
    np.testing.assert_allclose(out_v[: len(v)], v)  # old vertices stay; new ones are midpoints
    # Each new face lies in an old face and faces the same way: summed normals per old
    # plane are unchanged, so the summed area vector is too.
    area_vector = np.cross(out_v[out_f[:, 1]] - out_v[out_f[:, 0]],
                           out_v[out_f[:, 2]] - out_v[out_f[:, 0]]).sum(axis=0)
    np.testing.assert_allclose(area_vector, np.cross(v[f[:, 1]] - v[f[:, 0]],
                                                     v[f[:, 2]] - v[f[:, 0]]).sum(axis=0),
                               atol=1e-9)


@settings(max_examples=40, deadline=None)
@given(subdivisions=st.integers(2, 4), cut=st.floats(0.0, 0.9), coarse=st.floats(0.0, 1.0),
       target_m=st.floats(0.005, 0.2), seed=st.integers(0, 2**16), rings=st.integers(0, 6))
def test_the_rounds_near_the_long_edges_equal_the_rounds_on_the_whole_mesh(
    subdivisions: int, cut: float, coarse: float, target_m: float, seed: int, rings: int,
) -> None:
    """A fine sphere cut open, part of it near the cut left coarse (long fans at the
    boundary, chains that run into the fine part): the same vertices and faces in the same
    order as the rounds over every face, whether the region's chains stay inside it or one
    reaches its rim (few rings) and the rounds go to the whole mesh."""
    from unittest import mock

    from pipeline.reconstruct.remesh import boundary_split

    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=0.5)
    rng = np.random.default_rng(seed)
    v = np.asarray(sphere.vertices) * (1 + 0.05 * rng.random((len(sphere.vertices), 1)))
    f = np.asarray(sphere.faces, np.int32)
    f = f[v[f].mean(axis=1)[:, 2] < 0.5 - cut]
    # Merge a band of faces into a coarse fan: drop them and close the hole with a fan
    # whose hub is a boundary vertex of the band.
    band = np.flatnonzero(v[f].mean(axis=1)[:, 0] > 0.5 - coarse * 0.5)
    f = np.delete(f, band[: len(band) // 2], axis=0)
    used = np.unique(f)
    v, f = v[used], np.searchsorted(used, f).astype(np.int32)
    expected_v, expected_f = split_everywhere(v, f, target_m)
    with mock.patch.object(boundary_split, "REGION_RINGS", rings):
        out_v, out_f = split_boundary_edges(v, f, target_m)
        # The faces' edge table made beforehand (`speculative.checked_faces`) changes nothing.
        given_v, given_f, _ = split_boundary_edges_with_parents(v, f, target_m, edge_table(f))
    np.testing.assert_array_equal(out_v, expected_v)
    np.testing.assert_array_equal(out_f, expected_f)
    np.testing.assert_array_equal(given_v, expected_v)
    np.testing.assert_array_equal(given_f, expected_f)


def test_a_chain_that_reaches_the_region_rim_is_refused() -> None:
    """Three faces in a row, the region the first two: the second's longest edge, which a
    chain from the first needs, is the third's too, so it is on the region's rim and the
    region's rounds give up (the caller then runs them on the whole mesh)."""
    from pipeline.reconstruct.remesh.boundary_split import _split_in_region

    v = np.array([[0, 0, 0], [1, 0, 0], [0.4, 2, 0], [2.2, 0.3, 0], [2.5, 3, 0]], float)
    f = np.array([[0, 1, 2], [1, 3, 2], [2, 3, 4]], dtype=np.int32)
    edges, opposite = edge_table(f)
    boundary_edges = edges[faces_per_edge(opposite, len(edges)) == 1]
    on_boundary = np.ones(len(v), dtype=bool)
    assert _split_in_region(v, f, np.array([0, 1]), boundary_edges, on_boundary, 0.1) is None
    whole = _split_in_region(v, f, np.array([0, 1, 2]), boundary_edges, on_boundary, 0.1)
    assert whole is not None
    np.testing.assert_array_equal(whole[1], split_everywhere(v, f, 0.1)[1])
    np.testing.assert_array_equal(split_boundary_edges(v, f, 0.1)[1], whole[1])
