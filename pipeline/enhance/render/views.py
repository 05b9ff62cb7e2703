"""Orthographic depth renders of a mesh from several directions around its bounding sphere:
the render stage's entry. `render_depth` picks the renderer, open3d's ray cast on the host
(`ray_cast`) or the torch rasterizer on a device (`rasterize`); both share the cameras and
render types of `camera`, and neither imports the other."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from pipeline.enhance.render.camera import (
    DepthRenders,
    ViewSet,
    make_views,
    project,
    view_directions,
)
from pipeline.geometry.mesh import TriangleMesh

__all__ = ["DepthRenders", "ViewSet", "canny_edges", "make_views", "project", "render_depth",
           "view_directions"]


def render_depth(
    mesh: TriangleMesh, views: ViewSet, with_color: bool = True, device: str | None = None
) -> DepthRenders:
    """Normalised depth (and interpolated vertex colour when present) for every view: ray-cast
    by open3d on the CPU when `device` is None, else rasterized by torch on that device (cpu,
    cuda), which agrees but for silhouette pixel centres that lie on an edge."""
    if mesh.face_count == 0:
        raise ValueError("mesh has no faces")
    if device is None:
        from pipeline.enhance.render import ray_cast

        return ray_cast.depth_renders(mesh, views, with_color)
    from pipeline.enhance.render import rasterize

    return rasterize.depth_renders(mesh, views, with_color, device)


def canny_edges(
    color_rgb: NDArray[np.uint8] | None, valid: NDArray[np.bool_]
) -> NDArray[np.float32] | None:
    """(N, H, W) float32 Canny edges (0/1) of (N, H, W, 3) colour renders on the surface, or
    None without colour: the networks' colour-edge input."""
    if color_rgb is None:
        return None
    import cv2

    out = np.zeros(valid.shape, np.float32)
    for k in range(len(color_rgb)):
        gray = cv2.cvtColor(color_rgb[k], cv2.COLOR_RGB2GRAY)
        out[k] = (cv2.Canny(gray, 50, 150) > 0) & valid[k]
    return out
