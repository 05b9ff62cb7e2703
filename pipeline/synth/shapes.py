"""Procedural meshes that need no files: the built-in sample subject and test shapes."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from pipeline.geometry.mesh import TriangleMesh

# (centre height, radius) of the snowman's three balls, metres: 1.8 m tall, a pinched neck.
_SNOWMAN_BALLS = ((0.42, 0.42), (1.08, 0.32), (1.58, 0.22))


def revolution_mesh(heights_m: NDArray[np.float64], radii_m: NDArray[np.float64],
                    azimuth_count: int) -> TriangleMesh:
    """A closed surface of rings about the +Y axis, CCW seen from outside.

    heights_m: (R,) increasing heights, metres; radii_m: (R, A) radius per height and azimuth
    (azimuth i at 2 pi i / A, from +Z towards +X). The first and last heights are the poles,
    single vertices on the axis (their radii are ignored).
    """
    rings, segments = radii_m.shape
    if heights_m.shape != (rings,) or segments != azimuth_count or rings < 3:
        raise ValueError("radii_m: expected (R >= 3, azimuth_count) radii for R heights")
    azimuth = 2 * np.pi * np.arange(segments) / segments
    inner = radii_m[1:-1]
    ring_vertices = np.stack([inner * np.sin(azimuth),
                              np.broadcast_to(heights_m[1:-1, None], inner.shape),
                              inner * np.cos(azimuth)], axis=-1).reshape(-1, 3)
    vertices = np.vstack([[0.0, heights_m[0], 0.0], ring_vertices, [0.0, heights_m[-1], 0.0]])
    top = len(vertices) - 1
    count = rings - 2
    j = np.arange(segments)
    nxt = (j + 1) % segments
    faces = [np.stack([np.zeros(segments, int), 1 + nxt, 1 + j], axis=1)]
    for i in range(count - 1):
        a, b = 1 + i * segments + j, 1 + i * segments + nxt
        c, d = a + segments, b + segments
        faces += [np.stack([a, b, d], axis=1), np.stack([a, d, c], axis=1)]
    last = 1 + (count - 1) * segments
    faces.append(np.stack([np.full(segments, top), last + j, last + nxt], axis=1))
    tri = np.vstack(faces).astype(np.int32)
    if _signed_volume(vertices, tri) < 0:
        tri = tri[:, ::-1].copy()
    return TriangleMesh(vertices_m=vertices, faces=tri)


def _signed_volume(vertices: NDArray[np.float64], faces: NDArray[np.int32]) -> float:
    a, b, c = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def snowman_mesh(ring_count: int = 160, azimuth_count: int = 192) -> TriangleMesh:
    """A 1.8 m snowman standing on y = 0: three merged balls, a pinched neck, gentle bumps.

    Closed and manifold, about 2 * ring_count * azimuth_count triangles (61k by default).
    """
    bottom = min(c - r for c, r in _SNOWMAN_BALLS)
    top = max(c + r for c, r in _SNOWMAN_BALLS)
    # Rings crowd towards the poles, where the radius changes fastest.
    t = np.linspace(0.0, 1.0, ring_count + 2)
    heights = bottom + (top - bottom) * (1.0 - np.cos(np.pi * t)) / 2.0
    profiles = np.stack([np.sqrt(np.clip(r**2 - (heights - c) ** 2, 0.0, None))
                         for c, r in _SNOWMAN_BALLS])
    # A p-norm is a smooth maximum: the balls melt into each other without a crease.
    radius = np.sum(profiles**6, axis=0) ** (1.0 / 6.0)
    azimuth = 2 * np.pi * np.arange(azimuth_count) / azimuth_count
    bumps = (1.0 + 0.06 * np.cos(2 * azimuth[None, :])
             + 0.025 * np.sin(7 * azimuth[None, :] + 11.0 * heights[:, None]))
    return revolution_mesh(heights, radius[:, None] * bumps, azimuth_count)


def uv_sphere_mesh(radius_m: float, ring_count: int = 96, azimuth_count: int = 128
                   ) -> TriangleMesh:
    """A sphere centred at the origin; vertices lie exactly on it (for analytic checks)."""
    polar = np.linspace(0.0, np.pi, ring_count + 2)
    heights = -radius_m * np.cos(polar)
    radii = np.repeat((radius_m * np.sin(polar))[:, None], azimuth_count, axis=1)
    return revolution_mesh(heights, radii, azimuth_count)
