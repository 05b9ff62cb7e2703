"""Meshes the pipeline's tests build themselves: spheres, and noisy shapes where flat faces meet
sharp edges."""

from __future__ import annotations

import numpy as np

from pipeline.geometry.mesh import TriangleMesh


def sphere(radius_m: float = 0.5, resolution: int = 24) -> TriangleMesh:
    import open3d as o3d

    m = o3d.geometry.TriangleMesh.create_sphere(radius_m, resolution)
    m.remove_duplicated_vertices()
    return TriangleMesh(np.asarray(m.vertices).copy(), np.asarray(m.triangles).astype(np.int32))


def radial_rms_m(mesh: TriangleMesh, radius_m: float = 0.5) -> float:
    """RMS distance of the vertices to the ideal sphere."""
    r = np.linalg.norm(mesh.vertices_m, axis=1)
    return float(np.sqrt(np.mean((r - radius_m) ** 2)))


def flat_meets_sharp(kind: int) -> tuple[TriangleMesh, TriangleMesh]:
    """(clean, noisy): the procedural shape `kind` (2 a box, 3 a cylinder) at unit extent,
    remeshed to 2 cm edges, its vertices moved along normals by noise in ±4 cm, seeded."""
    from pipeline.enhance.training.data import (
        isotropic,
        noisy_along_normals,
        procedural_meshes,
        unit_extent,
    )

    name, mesh = procedural_meshes(np.random.default_rng(0), 5)[kind]
    clean = isotropic(unit_extent(mesh, name), 0.02)
    return clean, noisy_along_normals(clean, 0.04, np.random.default_rng(3))


def c2m_rms_m(mesh: TriangleMesh, truth: TriangleMesh) -> float:
    """RMS of the vertices' signed distances to `truth`."""
    from pipeline.enhance.metrics import signed_c2m

    return float(np.sqrt(np.mean(signed_c2m(mesh.vertices_m, truth) ** 2)))
