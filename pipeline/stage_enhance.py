"""The enhance stage: the noise gate, `pipeline.enhance.enhance_mesh` on a mesh past it, and
how far the surface moved."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from pipeline.reconstruct.quality import signed_distances_m
from pipeline.stage_artifacts import (
    Artifacts,
    CaptureReader,
    NetworksSource,
    Progress,
    mesh_from_artifacts,
    stats_artifact,
    tick,
)
from pipeline.stage_config import ReconstructConfig


def stage_enhance(capture: CaptureReader, inputs: Mapping[str, NDArray[Any]],
                  config: ReconstructConfig, progress: Progress | None,
                  networks: NetworksSource | None = None) -> Artifacts:
    """Enhance the latest mesh unless the gate finds it clean; `networks` is asked for only
    when the mesh is enhanced (None: `enhance_mesh` loads them)."""
    from pipeline.enhance import enhance_mesh
    from pipeline.enhance.enhancement import past_the_gate, skipped_at
    from pipeline.enhance.noise_level import noise_to_edge_ratio
    from pipeline.enhance.self_check import SelfCheck

    mesh = mesh_from_artifacts(inputs)
    # Measured once: the figures and the gate read the same ratio.
    noise_ratio = noise_to_edge_ratio(mesh)
    skipped = skipped_at(noise_ratio, config.enhancement)
    # A clean mesh is left as `enhance_mesh` leaves it, without loading its networks or
    # rendering its views.
    checks: list[SelfCheck] = []
    out = mesh if skipped else enhance_mesh(mesh, past_the_gate(config.enhancement), progress,
                                            networks() if networks is not None else None,
                                            checks.append)
    tick(progress, 1.0)
    # The light remesh renumbers vertices: how far the surface moved is measured against
    # the surface before, not vertex by vertex (a clean mesh has not moved).
    offset_m = np.zeros(1) if skipped else np.abs(signed_distances_m(out.vertices_m, mesh))
    result: Artifacts = {"vertices_m": out.vertices_m, "faces": out.faces}
    return result | stats_artifact("enhance", {
        "method": config.enhancement.method, "views": config.enhancement.views,
        "noise_ratio": noise_ratio, "skipped_as_clean": skipped,
        "triangles": out.face_count, "mean_offset_m": float(offset_m.mean()),
        "max_offset_m": float(offset_m.max()),
        "self_check": checks[0].as_stats() if checks else None})
