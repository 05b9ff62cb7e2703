"""The torch mesh quantities the GPU path uses are the numpy and scipy ones, to rounding."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.enhance import mesh_torch
from pipeline.enhance.training.data import noisy_along_normals
from pipeline.geometry.mesh import TriangleMesh, mean_edge_length_m, vertex_normals
from pipeline.geometry.repair import triangle_angles_deg
from pipeline.geometry.smoothing import mean_operator
from tests.pipeline.meshes import sphere


def _mesh(resolution: int, kept_share: float, isolated: int, seed: int) -> TriangleMesh:
    """A noisy sphere with faces dropped (open boundaries) and `isolated` unused vertices."""
    rng = np.random.default_rng(seed)
    mesh = noisy_along_normals(sphere(0.5, resolution), 0.01, rng)
    faces = mesh.faces[rng.random(mesh.face_count) < kept_share]
    extra = rng.normal(size=(isolated, 3))
    return TriangleMesh(np.vstack([mesh.vertices_m, extra]), faces.astype(np.int32))


MESHES = st.builds(_mesh, st.integers(6, 20), st.floats(0.3, 1.0), st.integers(0, 3),
                   st.integers(0, 2**31 - 1))


def _faces(mesh: TriangleMesh) -> torch.Tensor:
    return torch.from_numpy(mesh.faces.astype(np.int64))


@settings(max_examples=25, deadline=None)
@given(mesh=MESHES, self_weight=st.sampled_from([0.0, 0.5]))
def test_the_mean_operator_is_scipys(mesh: TriangleMesh, self_weight: float) -> None:
    expected = ((1 - self_weight) * mean_operator(mesh.faces, mesh.vertex_count)
                + self_weight * sp.identity(mesh.vertex_count)).tocsr()
    expected.sort_indices()
    expected.eliminate_zeros()
    pattern = mesh_torch.neighbour_pattern(_faces(mesh), mesh.vertex_count)
    got = mesh_torch.mean_operator(pattern, self_weight)
    np.testing.assert_array_equal(got.crow_indices().numpy(), expected.indptr)
    np.testing.assert_array_equal(got.col_indices().numpy(), expected.indices)
    np.testing.assert_allclose(got.values().numpy(), expected.data, rtol=1e-15, atol=0)


@settings(max_examples=25, deadline=None)
@given(mesh=MESHES)
def test_normals_and_edge_length_are_pipeline_meshs(mesh: TriangleMesh) -> None:
    vertices_m = torch.from_numpy(mesh.vertices_m)
    normals = mesh_torch.vertex_normals(vertices_m, _faces(mesh))
    assert normals.dtype == torch.float32
    np.testing.assert_allclose(normals.numpy(), vertex_normals(mesh.vertices_m, mesh.faces),
                               rtol=0, atol=2e-7)
    assert mesh_torch.mean_edge_length_m(vertices_m, _faces(mesh)) == pytest.approx(
        mean_edge_length_m(mesh), rel=1e-12)


@settings(max_examples=25, deadline=None)
@given(mesh=MESHES)
def test_angles_are_mesh_repairs(mesh: TriangleMesh) -> None:
    """The same steps in the same order: they differ by rounding alone, most where an angle
    is near 0 or 180 degrees. A face with a repeated corner gives 0 at each corner, and three
    corners in a line 0, 180 and 0, as there."""
    line = len(mesh.vertices_m) + np.arange(3)
    vertices_m = np.vstack([mesh.vertices_m, [[0.0, 0, 0], [1, 0, 0], [2, 0, 0]]])
    faces = np.vstack([mesh.faces, [[0, 0, 1], [2, 2, 2]], line[None]]).astype(np.int32)
    expected = triangle_angles_deg(vertices_m, faces)
    got = mesh_torch.triangle_angles_deg(torch.from_numpy(vertices_m),
                                         torch.from_numpy(faces.astype(np.int64)))
    assert got.dtype == torch.float64
    np.testing.assert_allclose(got.numpy(), expected, rtol=0, atol=1e-9)
    assert (got[-3:-1] == 0).all() and got[-1].tolist() == expected[-1].tolist()


@settings(max_examples=25, deadline=None)
@given(mesh=MESHES)
def test_faces_sharing_vertices_is_mesh_repairs_pattern(mesh: TriangleMesh) -> None:
    from pipeline.geometry.repair import faces_sharing_vertices

    expected = faces_sharing_vertices(mesh.faces, mesh.vertex_count).tocsr()
    expected.sort_indices()
    starts, columns = mesh_torch.faces_sharing_vertices(_faces(mesh), mesh.vertex_count)
    np.testing.assert_array_equal(starts.numpy(), expected.indptr)
    np.testing.assert_array_equal(columns.numpy(), expected.indices)


@settings(max_examples=25, deadline=None)
@given(mesh=MESHES)
def test_boundary_half_edges_are_boundarys(mesh: TriangleMesh) -> None:
    from pipeline.geometry.boundary import boundary_half_edges

    got = mesh_torch.boundary_half_edges(_faces(mesh), mesh.vertex_count)
    np.testing.assert_array_equal(got.numpy(), boundary_half_edges(mesh.faces))
