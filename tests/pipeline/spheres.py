"""Spheres the pipeline's tests build themselves: clean, and noisy along their normals."""

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
