"""Small meshes the enhancement tests build themselves."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.enhance.training.data import DepthPairs
from pipeline.geometry.mesh import TriangleMesh


def sphere(radius_m: float = 0.5, resolution: int = 24) -> TriangleMesh:
    import open3d as o3d

    m = o3d.geometry.TriangleMesh.create_sphere(radius_m, resolution)
    m.remove_duplicated_vertices()
    return TriangleMesh(np.asarray(m.vertices).copy(), np.asarray(m.triangles).astype(np.int32))


@pytest.fixture
def unit_sphere() -> TriangleMesh:
    return sphere()


@pytest.fixture
def noisy_sphere(unit_sphere: TriangleMesh) -> tuple[TriangleMesh, TriangleMesh]:
    """(clean, noisy): vertices moved along normals by uniform noise in ±1 cm, seeded."""
    from pipeline.enhance.training.data import noisy_along_normals

    return unit_sphere, noisy_along_normals(unit_sphere, 0.01, np.random.default_rng(0))


def radial_rms_m(mesh: TriangleMesh, radius_m: float = 0.5) -> float:
    """RMS distance of the vertices to the ideal sphere."""
    r = np.linalg.norm(mesh.vertices_m, axis=1)
    return float(np.sqrt(np.mean((r - radius_m) ** 2)))


def ramp_pairs(n: int = 3, side: int = 40) -> DepthPairs:
    """Pairs whose base depth is a unique ramp (each window identifiable by its minimum) and
    whose clean depth is the base plus 0.01; the mask covers the left 70 % of each image."""
    base = (np.arange(n * side * side, dtype=np.float32) / (n * side * side)).reshape(n, side, side)
    valid = np.ones_like(base, bool)
    mask = np.zeros_like(valid)
    mask[:, :, : int(0.7 * side)] = True
    return DepthPairs(base, valid, base.copy(), base + 0.01, mask, np.zeros_like(valid),
                      ("ramp",) * n)
