"""The light remesh that ends every enhancement: an isotropic remesh at the mesh's own mean edge
length, kept only where it leaves the surface whole and its angles no worse, then the remesh
stage's angle clean-up.

The update moves vertices and keeps the faces, which leaves slivers where the moves crowd; one
round of the isotropic kernel evens them out. Where the moved mesh keeps faces far longer than
its mean edge, one round of the kernel cuts across the surface instead, so its result is
judged (`LIGHT_REMESH_MAX_ADDED_OUTSIDE`, `LIGHT_REMESH_MAX_LOST_EDGES`) and dropped there.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from pipeline.geometry.mesh import TriangleMesh, mean_edge_length_m
from pipeline.reconstruct.remesh.isotropic import RemeshConfig, remesh
from pipeline.reconstruct.remesh.kernel import KernelChild

LIGHT_REMESH_MAX_ADDED_OUTSIDE = 2e-4
"""The kernel's result is dropped where it adds more than this share of faces outside the
angle criteria: there it folded the surface rather than evening it out."""

LIGHT_REMESH_MAX_LOST_EDGES = 2.0
"""The kernel's result is dropped where an input vertex ends up further than this many edge
lengths from every vertex of it (`remesh.surface_lost_edges`): it cut part of the surface
away."""

LIGHT_REMESH_GRID_M = 2.0**-32
"""The grid `light_remesh` snaps vertices to, metres (0.23 nm): far below any mesh's detail,
far above float64's rounding of coordinates of a few metres, and exact (a power of two) for
coordinates below 2^21 m."""


def light_remesh(mesh: TriangleMesh, iterations: int, children: Sequence[KernelChild] = ()
                 ) -> TriangleMesh:
    """The mesh remeshed at its own mean edge length (vertices projected back onto it), unless
    that adds faces outside the angle criteria or cuts part of the surface away, then its
    angles cleaned up. The kernel runs in spatial pieces side by side, one per core, in
    `children` where given (started beforehand, `kernel_children`).

    The mesh is first snapped to a grid of `LIGHT_REMESH_GRID_M`: the kernel compares edge
    lengths with each other and with the target, and where a mesh has edges of equal length
    (a symmetric one) a difference of rounding alone, such as a GPU's float64 sums against
    the host's, would choose other flips and give another mesh."""
    mesh = on_light_remesh_grid(mesh)
    return remesh(mesh, light_remesh_config(mesh, iterations), children)[0]


def on_light_remesh_grid(mesh: TriangleMesh) -> TriangleMesh:
    """`mesh` with its vertices snapped to `LIGHT_REMESH_GRID_M`."""
    return replace(mesh, vertices_m=np.round(mesh.vertices_m / LIGHT_REMESH_GRID_M)
                   * LIGHT_REMESH_GRID_M)


def light_remesh_config(mesh: TriangleMesh, iterations: int) -> RemeshConfig:
    """`light_remesh`'s settings for `mesh`: its own mean edge length, `iterations` rounds,
    the kernel judged and in pieces, one per core."""
    return RemeshConfig(target_edge_length_m=mean_edge_length_m(mesh), iterations=iterations,
                        max_kernel_added_outside=LIGHT_REMESH_MAX_ADDED_OUTSIDE,
                        max_kernel_lost_edges=LIGHT_REMESH_MAX_LOST_EDGES,
                        min_component_share=0.0, kernel_processes=None)
