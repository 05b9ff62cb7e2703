"""How noisy a mesh is, relative to its own edge length, from the mesh alone.

The networks correct the render of a mesh after Laplacian pre-smoothing; on a mesh that is
already clean (a good reconstruction, an enhanced mesh) that smoothing removes detail the
networks cannot restore, so the enhancement gates on this estimate.
"""

from __future__ import annotations

import numpy as np

from pipeline.enhance.baselines import mean_operator
from pipeline.mesh import TriangleMesh, mean_edge_length_m, vertex_normals


def noise_to_edge_ratio(mesh: TriangleMesh) -> float:
    """Robust vertex noise along the normals, as a fraction of the mean edge length.

    Each vertex's umbrella offset (mean of its neighbours minus itself) along its normal holds
    the surface's curvature, which varies smoothly, plus the vertex noise, which does not; the
    offset minus its neighbours' mean keeps the noise. The median of its magnitude over the
    mean edge length is scale-free: about 0.01 on a clean or well-reconstructed mesh, 0.11 for
    uniform noise along normals of amplitude 0.2 edge lengths, about 0.5 at two edge lengths
    (where it saturates).
    """
    m = mean_operator(mesh.faces, mesh.vertex_count)
    normals = vertex_normals(mesh.vertices_m, mesh.faces)
    umbrella_m = np.sum((m @ mesh.vertices_m - mesh.vertices_m) * normals, axis=1)
    rough_m = umbrella_m - m @ umbrella_m
    return float(np.median(np.abs(rough_m)) / mean_edge_length_m(mesh))
