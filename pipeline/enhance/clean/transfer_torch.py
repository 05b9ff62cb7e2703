"""The light remesh's carry (`pipeline.reconstruct.remesh.speculative.Carry`) on the
enhancement's device, the torch twin of `speculative.carried_with_angles`: on a GPU the finish
of the speculative remesh puts the kernel's result on the moved mesh (barycentric transfer)
and measures its angles there, not on the host."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from pipeline.enhance import mesh_torch
from pipeline.enhance.device import on_device
from pipeline.reconstruct.remesh.speculative import Carry


def carried_on(device: str) -> Carry:
    """`speculative.carried_with_angles` on `device`, float64 there, the arrays copied over
    and back."""

    def carry(vertices_m: NDArray[np.float64], source_ids: NDArray[np.int64],
              source_weights: NDArray[np.float64], faces: NDArray[np.int32]
              ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        corners_m = on_device(vertices_m, device)[on_device(source_ids, device)]
        carried_m = (on_device(source_weights, device)[..., None] * corners_m).sum(dim=1)
        angles = mesh_torch.triangle_angles_deg(carried_m, on_device(faces, device).long())
        return carried_m.cpu().numpy(), angles.cpu().numpy()

    return carry
