"""Moves a mesh's vertices along view rays to enhanced depth images: the update stage's entry.

Each function here picks the implementation by `device`: numpy and scipy on the host
(`steps_numpy`, device None) or torch on that device (`steps_torch`). Both share the settings
and step types of `steps_common`, and neither imports the other."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from pipeline.enhance.render.camera import DepthRenders
from pipeline.enhance.update import steps_numpy
from pipeline.enhance.update.steps_common import UpdateConfig, ViewSteps
from pipeline.geometry.mesh import TriangleMesh

__all__ = ["UpdateConfig", "ViewSteps", "apply_view_steps", "update_vertices", "view_steps"]


def view_steps(
    mesh: TriangleMesh,
    renders: DepthRenders,
    enhanced_depth_n: NDArray[np.float32],
    config: UpdateConfig,
    device: str | None = None,
) -> ViewSteps:
    """Each view's step for each vertex toward the enhanced depth (`enhanced_depth_n`, (N, H, W)
    normalised depth of the views of `renders`, the mesh's own renders). In torch float64 on
    `device` ("cpu", "cuda") where given, else in numpy."""
    if enhanced_depth_n.shape != renders.depth_n.shape:
        raise ValueError(
            f"enhanced_depth_n has shape {enhanced_depth_n.shape}, renders {renders.depth_n.shape}"
        )
    if device is None:
        return steps_numpy.view_steps(mesh, renders, enhanced_depth_n, config)
    from pipeline.enhance.update import steps_torch

    return steps_torch.view_steps(mesh, renders, enhanced_depth_n, config, device)


def update_vertices(
    mesh: TriangleMesh,
    renders: DepthRenders,
    enhanced_depth_n: NDArray[np.float32],
    config: UpdateConfig,
    vertex_gain: NDArray[np.float64] | None = None,
    device: str | None = None,
) -> tuple[TriangleMesh, NDArray[np.bool_]]:
    """The mesh with vertices moved to the enhanced depth, and the (V,) mask of seen vertices.

    `renders` are the mesh's own renders (for the visibility depth test); `enhanced_depth_n`
    (N, H, W) the enhanced normalised depth of the same views; `device` as `view_steps`'.
    """
    steps = view_steps(mesh, renders, enhanced_depth_n, config, device)
    return apply_view_steps(mesh, steps, config, vertex_gain, device)


def apply_view_steps(
    mesh: TriangleMesh,
    steps: ViewSteps,
    config: UpdateConfig,
    vertex_gain: NDArray[np.float64] | None = None,
    device: str | None = None,
) -> tuple[TriangleMesh, NDArray[np.bool_]]:
    """The mesh with each seen vertex moved by the weighted average of its views' steps (times
    its `vertex_gain`, (V,), when given), capped; the unseen moved by the smooth interpolation
    of their seen neighbours' moves; folds put back. Also the (V,) mask of seen vertices. In
    torch float64 on `device` where given."""
    if device is None:
        return steps_numpy.apply_view_steps(mesh, steps, config, vertex_gain)
    from pipeline.enhance.update import steps_torch

    return steps_torch.apply_view_steps(mesh, steps, config, vertex_gain, device)
