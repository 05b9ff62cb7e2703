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


def grid(n: int, spacing_m: float = 0.01) -> TriangleMesh:
    """An n x n vertex square in the z = 0 plane, its faces wound to face +z."""
    x, y = np.meshgrid(np.arange(n) * spacing_m, np.arange(n) * spacing_m, indexing="ij")
    v = np.column_stack([x.ravel(), y.ravel(), np.zeros(n * n)])
    i = np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None, :]
    i = i.ravel()
    faces = np.concatenate([np.column_stack([i, i + n, i + 1]),
                            np.column_stack([i + 1, i + n, i + n + 1])]).astype(np.int32)
    return TriangleMesh(v, faces)


def cube(cells: int) -> TriangleMesh:
    """The surface of the cube [-0.5, 0.5]³, each side a grid of `cells` x `cells` squares cut
    in two, its faces wound outwards: flat sides meeting at sharp edges."""
    t = np.linspace(-0.5, 0.5, cells + 1)
    u, w = (a.ravel() for a in np.meshgrid(t, t, indexing="ij"))
    square = grid(cells + 1).faces
    vertices: list[np.ndarray] = []
    faces: list[np.ndarray] = []
    for axis in range(3):
        first, second = (axis + 1) % 3, (axis + 2) % 3  # first × second points along +axis
        for sign in (-1.0, 1.0):
            side = np.zeros((len(u), 3))
            side[:, axis], side[:, first], side[:, second] = sign * 0.5, u, w
            wound = square if sign > 0 else square[:, ::-1]
            faces.append(wound + len(vertices) * len(u))
            vertices.append(side)
    v, f = np.concatenate(vertices), np.concatenate(faces)
    # The sides share their rims: one vertex for each point.
    _, first_of, merged = np.unique(np.round(v * 2 * cells).astype(np.int64), axis=0,
                                    return_index=True, return_inverse=True)
    return TriangleMesh(v[first_of], merged.ravel()[f].astype(np.int32))


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
