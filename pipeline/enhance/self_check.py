"""Whether the networks help on this mesh, checked on a simulated copy whose truth is known.

The networks' correction of the pre-smoothed base helps on some meshes and harms on others,
and no per-vertex signal tells which. A residual bootstrap does: the classical result (the
base, then the normal filter) stands in for the truth, the input's own residuals from the
base, shuffled among the vertices, make a copy of it as noisy as the input, and that copy is
enhanced with the networks and without them. Whichever lands nearer the stand-in is the one
kept (`benchmarks/enhance_self_check.py` scores the choice).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from pipeline.geometry.mesh import TriangleMesh, vertex_normals
from pipeline.reconstruct.quality import signed_distances_m


@dataclass(frozen=True)
class SelfCheck:
    """How far the simulated copy, enhanced each way, landed from its truth."""

    without_networks_rms_m: float
    """C2M RMS of the copy's classical result (the base, then the normal filter)."""
    with_networks_rms_m: float
    """C2M RMS of the copy's result with the networks' update."""

    @property
    def networks_help(self) -> bool:
        return self.with_networks_rms_m < self.without_networks_rms_m

    def as_stats(self) -> dict[str, float | bool]:
        return {"networks_help": self.networks_help,
                "without_networks_rms_mm": self.without_networks_rms_m * 1e3,
                "with_networks_rms_mm": self.with_networks_rms_m * 1e3}


def residuals_m(mesh: TriangleMesh, base: TriangleMesh) -> NDArray[np.float64]:
    """(V,) each vertex's offset from the base along the base's vertex normal, metres; the
    pre-smoothing moves vertices only, so the two share their faces."""
    normals = vertex_normals(base.vertices_m, base.faces).astype(np.float64)
    return np.einsum("ij,ij->i", mesh.vertices_m - base.vertices_m, normals)


def simulated_copy(mesh: TriangleMesh, base: TriangleMesh, truth: TriangleMesh, seed: int
                   ) -> TriangleMesh:
    """`truth` (the base's faces) with `mesh`'s residuals from `base`, shuffled among the
    vertices with `seed`, along its own normals: noise of the input's distribution (uniform,
    Gaussian or other) on a surface whose truth is known."""
    offsets_m = np.random.default_rng(seed).permutation(residuals_m(mesh, base))
    normals = vertex_normals(truth.vertices_m, truth.faces).astype(np.float64)
    return truth.with_vertices(truth.vertices_m + normals * offsets_m[:, None])


def scored(without_networks: TriangleMesh, with_networks: TriangleMesh, truth: TriangleMesh
           ) -> SelfCheck:
    """The copy's two results scored against its truth, both in one query of its surface
    (built once: building it is most of a query's time)."""
    points_m = np.concatenate([without_networks.vertices_m, with_networks.vertices_m])
    squared = signed_distances_m(points_m, truth) ** 2
    split = without_networks.vertex_count
    return SelfCheck(float(np.sqrt(squared[:split].mean())),
                     float(np.sqrt(squared[split:].mean())))
