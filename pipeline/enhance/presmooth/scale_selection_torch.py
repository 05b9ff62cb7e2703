"""The twicings' smoothing steps (`FieldOps`) in torch on a device, built from the faces there
(`scale_selection` chooses these or `scale_selection_numpy`'s): the mean operator, the
smoothing step and the open boundary's offset never pass through scipy, so on a GPU the
selector's candidates and features are made there."""

from __future__ import annotations

import numpy as np
import torch

from pipeline.enhance import mesh_torch
from pipeline.enhance.device import on_device
from pipeline.enhance.presmooth.scale_selection_common import FieldOps, leaving_out
from pipeline.geometry.mesh import TriangleMesh


def mesh_field_ops(mesh: TriangleMesh, boundary_pilot_iterations: int, device: str
                    ) -> FieldOps:
    """The mesh's `FieldOps` on `device`, steps leaving out the boundary offset measured
    after `boundary_pilot_iterations` steps (0: none)."""
    faces = on_device(mesh.faces.astype(np.int64), device)
    pattern = mesh_torch.neighbour_pattern(faces, mesh.vertex_count)
    mean = mesh_torch.mean_operator(pattern)
    half_step = mesh_torch.mean_operator(pattern, self_weight=0.5)
    average = mesh_torch.mean_operator(pattern, dtype=torch.float32)
    offset_m = boundary_offset(mesh, faces, mean, half_step, boundary_pilot_iterations)

    def to_field(x: np.ndarray) -> torch.Tensor:
        return on_device(x, device)

    return FieldOps(
        step=leaving_out(lambda y: half_step @ y, offset_m, to_field),
        average=lambda y: average @ y,
        to_field=to_field,
        to_numpy=lambda t: t.cpu().numpy(),
        mean=lambda y: mean @ y,
        normals=lambda y: mesh_torch.vertex_normals(y, faces).double(),
        columns=lambda columns: torch.stack(columns, 1).float(),
    )


def boundary_offset(mesh: TriangleMesh, faces: torch.Tensor, mean: torch.Tensor,
                    half_step: torch.Tensor, pilot_iterations: int) -> np.ndarray | None:
    """`pipeline.geometry.boundary.boundary_offset` with its pilot steps, normals and offset
    on the faces' device (`mean` and `half_step` the mesh's `mesh_torch.mean_operator` at
    self-weights 0 and 0.5); (V, 3) on the host, or None."""
    if pilot_iterations == 0:
        return None
    half = mesh_torch.boundary_half_edges(faces, mesh.vertex_count)
    if len(half) == 0:
        return None
    pilot = on_device(mesh.vertices_m, faces.device.type)
    for _ in range(pilot_iterations):
        pilot = half_step @ pilot
    along = pilot[half[:, 1]] - pilot[half[:, 0]]
    tangent = torch.zeros_like(pilot)
    for end in (0, 1):
        tangent.index_add_(0, half[:, end], along)
    across = torch.linalg.cross(mesh_torch.vertex_normals(pilot, faces).double(), tangent)
    length = torch.linalg.vector_norm(across, dim=1, keepdim=True)
    across = torch.where(length > 0, across / length.clamp_min(1e-300), 0.0)
    offset = torch.sum((mean @ pilot - pilot) * across, dim=1, keepdim=True)
    return (offset * across).cpu().numpy()
