"""The light remesh's carry on the enhancement's device (`transfer_torch`) against numpy's."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pipeline.enhance.clean.transfer_torch import carried_on
from pipeline.enhance.training.data import noisy_along_normals
from pipeline.reconstruct.remesh.speculative import carried_with_angles
from tests.pipeline.meshes import sphere


def _carry_inputs(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A noisy sphere's vertices, points on its faces' corners with barycentric weights (one
    a vertex itself: weights 1, 0, 0) and faces over those points."""
    rng = np.random.default_rng(seed)
    mesh = noisy_along_normals(sphere(0.5, 16), 0.01, rng)
    corners = mesh.faces[rng.integers(0, mesh.face_count, mesh.vertex_count)].astype(np.int64)
    weights = rng.random(corners.shape)
    weights /= weights.sum(axis=1, keepdims=True)
    weights[0] = (1.0, 0.0, 0.0)
    return mesh.vertices_m, corners, weights, mesh.faces


@pytest.mark.parametrize("device", [
    "cpu",
    pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(),
                                                  reason="no CUDA device")),
])
def test_the_carry_on_a_device_is_numpys(device: str) -> None:
    vertices_m, ids, weights, faces = _carry_inputs(0)
    expected_m, expected_deg = carried_with_angles(vertices_m, ids, weights, faces)
    got_m, got_deg = carried_on(device)(vertices_m, ids, weights, faces)
    assert got_m.dtype == np.float64 and got_deg.shape == faces.shape
    np.testing.assert_allclose(got_m, expected_m, rtol=0, atol=1e-15)
    np.testing.assert_allclose(got_deg, expected_deg, rtol=0, atol=1e-9)
    assert np.array_equal(got_m[0], vertices_m[ids[0, 0]])  # a vertex carried as itself
    assert not np.allclose(got_m, vertices_m)  # the points are not the vertices
