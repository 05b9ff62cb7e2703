"""Depth renders by open3d's ray cast on the host: one ray per pixel centre from the near
plane along the view's forward axis (`camera`'s conventions)."""

from __future__ import annotations

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from pipeline.enhance.render.camera import DepthRenders, ViewSet
from pipeline.geometry.mesh import TriangleMesh


def _ray_grid(views: ViewSet) -> NDArray[np.float32]:
    """(N, H, W, 6) ray origins (on the near plane) and directions, metres."""
    res, h = views.resolution, views.half_extent_m
    s = ((np.arange(res) + 0.5) / res * 2.0 - 1.0) * h
    ys, xs = np.meshgrid(s, s, indexing="ij")
    near = views.center_m[None] - views.forwards * h  # (N, 3)
    origins = (
        near[:, None, None, :]
        + xs[None, :, :, None] * views.rights[:, None, None, :]
        + ys[None, :, :, None] * views.downs[:, None, None, :]
    )
    dirs = np.broadcast_to(views.forwards[:, None, None, :], origins.shape)
    return np.concatenate([origins, dirs], axis=-1).astype(np.float32)


def depth_renders(mesh: TriangleMesh, views: ViewSet, with_color: bool) -> DepthRenders:
    """Normalised depth for every view of `mesh` (at least one face), and its interpolated
    vertex colour where `with_color` and the mesh has colours."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor.from_numpy(mesh.vertices_m.astype(np.float32)),
        o3d.core.Tensor.from_numpy(mesh.faces.astype(np.uint32)),
    )
    hits = scene.cast_rays(o3d.core.Tensor.from_numpy(_ray_grid(views)), nthreads=0)
    t_hit = hits["t_hit"].numpy()
    valid = np.isfinite(t_hit)
    depth = np.where(valid, t_hit / views.depth_range_m, 1.0).astype(np.float32)
    np.clip(depth, 0.0, 1.0, out=depth)
    color = None
    if with_color and mesh.vertex_colors is not None:
        prim = np.where(valid, hits["primitive_ids"].numpy(), 0).astype(np.int64)
        uv = hits["primitive_uvs"].numpy()
        corners = mesh.vertex_colors[mesh.faces[prim]].astype(np.float32)  # (..., 3, 3)
        w = np.stack([1.0 - uv[..., 0] - uv[..., 1], uv[..., 0], uv[..., 1]], axis=-1)
        rgb = np.sum(corners * w[..., None], axis=-2)
        color = np.where(valid[..., None], np.clip(rgb, 0, 255), 0).astype(np.uint8)
    return DepthRenders(views, depth, valid, color)


