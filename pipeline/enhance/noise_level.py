"""How noisy a mesh is, relative to its own edge length, from the mesh alone, and the noise
gate that reads it.

Every method pre-smooths the mesh; on a mesh that is already clean (a good reconstruction,
an enhanced mesh) that smoothing removes detail nothing restores, so the enhancement returns
a mesh whose estimated noise is below `EnhanceConfig.min_noise_ratio` as it came.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from pipeline.enhance.config import EnhanceConfig
from pipeline.geometry.mesh import TriangleMesh, mean_edge_length_m, vertex_normals
from pipeline.geometry.smoothing import mean_operator


def noise_to_edge_ratio(mesh: TriangleMesh, device: str | None = None) -> float:
    """Robust vertex noise along the normals, as a fraction of the mean edge length.

    Each vertex's umbrella offset (mean of its neighbours minus itself) along its normal holds
    the surface's curvature, which varies smoothly, plus the vertex noise, which does not; the
    offset minus its neighbours' mean keeps the noise. The median of its magnitude over the
    mean edge length is scale-free: about 0.01 on a clean or well-reconstructed mesh, 0.11 for
    uniform noise along normals of amplitude 0.2 edge lengths, about 0.5 at two edge lengths
    (where it saturates). On a torch `device` where given (`noise_to_edge_ratio_torch`), else
    in numpy.
    """
    if device is not None:
        return noise_to_edge_ratio_torch(mesh, device)
    m = mean_operator(mesh.faces, mesh.vertex_count)
    normals = vertex_normals(mesh.vertices_m, mesh.faces)
    umbrella_m = np.sum((m @ mesh.vertices_m - mesh.vertices_m) * normals, axis=1)
    rough_m = umbrella_m - m @ umbrella_m
    return float(np.median(np.abs(rough_m)) / mean_edge_length_m(mesh))


def noise_to_edge_ratio_torch(mesh: TriangleMesh, device: str) -> float:
    """`noise_to_edge_ratio` in torch on `device` (float64)."""
    import torch

    from pipeline.enhance import mesh_torch
    from pipeline.enhance.device import on_device

    vertices_m = on_device(mesh.vertices_m, device)
    faces = on_device(mesh.faces.astype(np.int64), device)
    m = mesh_torch.mean_operator(mesh_torch.neighbour_pattern(faces, mesh.vertex_count))
    normals = mesh_torch.vertex_normals(vertices_m, faces).double()
    umbrella_m = torch.sum((m @ vertices_m - vertices_m) * normals, dim=1)
    rough_m = umbrella_m - m @ umbrella_m
    return float(_median(rough_m.abs())) / mesh_torch.mean_edge_length_m(vertices_m, faces)


def _median(values):
    """numpy's median: the mean of the two middle values of an even count."""
    ordered = values.sort().values
    middle = (len(ordered) - 1) // 2
    return 0.5 * (ordered[middle] + ordered[len(ordered) // 2])


def skips_enhancement(mesh: TriangleMesh, config: EnhanceConfig, device: str | None = None
                      ) -> bool:
    """Whether `enhance_mesh` returns `mesh` as it came: its estimated noise is below
    `config.min_noise_ratio` (estimated on `device` where it is an accelerator)."""
    if not gated(config):
        return False
    from pipeline.enhance.device import accelerator

    return skipped_at(noise_to_edge_ratio(mesh, accelerator(device)), config)


def gated(config: EnhanceConfig) -> bool:
    """Whether `config` returns a mesh less noisy than `min_noise_ratio` as it came."""
    return config.min_noise_ratio > 0


def skipped_at(noise_ratio: float, config: EnhanceConfig) -> bool:
    """Whether `enhance_mesh` returns a mesh of this `noise_to_edge_ratio` as it came."""
    return gated(config) and noise_ratio < config.min_noise_ratio


def past_the_gate(config: EnhanceConfig) -> EnhanceConfig:
    """`config` for a mesh its caller has already measured past the noise gate
    (`skipped_at`): `enhance_mesh` then neither measures the noise again nor decides
    otherwise, on a GPU in torch, near the line."""
    return replace(config, min_noise_ratio=0.0)
