"""Depth renders by an orthographic rasterizer in torch, on any torch device: the same
renders as `ray_cast`'s but for silhouette pixel centres that lie on an edge.

Each (view, face) pair lists the pixel centres inside its projected bounding box; an edge test
keeps those the face covers, and a per-pixel minimum over (depth, face) keys picks the nearest
face. Conventions follow `camera`: pixel (row i, column j) sits at
((j + 0.5) / res * 2 - 1) * half_extent along the view's right (and the same with i along its
down), depth runs along forward from the near plane and is normalised by the depth range.
"""

from __future__ import annotations

import numpy as np
import torch
from numpy.typing import NDArray

from pipeline.enhance.render.camera import DepthRenders, ViewSet
from pipeline.geometry.mesh import TriangleMesh

_NO_HIT = torch.iinfo(torch.int64).max
_FACE_BITS = 32
_FACE_MASK = (1 << _FACE_BITS) - 1

DEFAULT_MAX_CANDIDATES = 1 << 21
"""Candidate (view, face, pixel) triples handled at once: bounds the working memory (a few
hundred bytes a candidate); a single face's box is never split."""


def depth_renders(mesh: TriangleMesh, views: ViewSet, with_color: bool, device: str
                  ) -> DepthRenders:
    """Normalised depth for every view of `mesh` (at least one face), and its interpolated
    vertex colour where `with_color` and the mesh has colours, rasterized on `device`."""
    colors = mesh.vertex_colors if with_color else None
    depth, valid, color = rasterize_depth(
        mesh.vertices_m, mesh.faces, views, device, vertex_colors=colors
    )
    return DepthRenders(views, depth, valid, color)


def rasterize_depth(
    vertices_m: NDArray[np.float64],
    faces: NDArray[np.integer],
    views: ViewSet,
    device: str,
    vertex_colors: NDArray[np.uint8] | None = None,
    max_candidates: int = DEFAULT_MAX_CANDIDATES,
    dtype: torch.dtype | None = None,
) -> tuple[NDArray[np.float32], NDArray[np.bool_], NDArray[np.uint8] | None]:
    """Normalised depth (N, H, W) float32 (1 where nothing is hit), the hit mask (N, H, W) and,
    with (V, 3) `vertex_colors`, interpolated colour (N, H, W, 3) uint8 (0 off the surface) of
    the mesh `vertices_m` (V, 3), `faces` (F, 3) seen from `views`, computed on `device` in
    `dtype` (None: float64 on the CPU, float32 elsewhere)."""
    dev = torch.device(device)
    if dtype is None:
        # float64 is cheap on the CPU; on a GPU float32 is what the hardware does fast.
        dtype = torch.float64 if dev.type == "cpu" else torch.float32
    # Projection in float64 on the device: only the mesh itself crosses from the host.
    vertices = torch.from_numpy(np.ascontiguousarray(vertices_m, np.float64)).to(dev)
    pix, z_n = (t.to(dtype) for t in project_px(vertices, views))  # (N, V, 2), (N, V)
    face_idx = torch.from_numpy(np.ascontiguousarray(faces)).to(dev).long()  # (F, 3)
    keys = _nearest_keys(pix, z_n, face_idx, views.resolution, max_candidates)
    valid = keys != _NO_HIT
    depth_bits = (keys >> _FACE_BITS).to(torch.int32)
    depth = torch.where(valid, depth_bits.view(torch.float32).clamp(0.0, 1.0), 1.0)
    color = None
    if vertex_colors is not None:
        colors = torch.from_numpy(np.ascontiguousarray(vertex_colors)).to(dev).to(dtype)
        color = _pixel_colors(pix, face_idx, colors, keys & _FACE_MASK, valid, views.resolution)
    shape = (views.count, views.resolution, views.resolution)
    return (
        depth.reshape(shape).cpu().numpy(),
        valid.reshape(shape).cpu().numpy(),
        None if color is None else color.reshape(*shape, 3).cpu().numpy(),
    )


def project_px(vertices_m: torch.Tensor, views: ViewSet) -> tuple[torch.Tensor, torch.Tensor]:
    """Vertex positions (N, V, 2) as (column, row) in pixels, pixel centres on integers, and
    normalised depth (N, V) from each view's near plane, of `vertices_m` (V, 3), in its dtype
    and on its device: `camera.project` in torch."""
    axes = np.stack([views.rights, views.downs, views.forwards], axis=1)  # (N, 3, 3)
    axes_t = torch.from_numpy(axes).to(vertices_m.device, vertices_m.dtype)
    center = torch.from_numpy(views.center_m).to(vertices_m.device, vertices_m.dtype)
    h = views.half_extent_m
    camera = torch.einsum("vk,nak->nva", vertices_m - center, axes_t) + h  # (N, V, 3)
    pix = camera[..., :2] * (views.resolution / (2.0 * h)) - 0.5
    return pix, camera[..., 2] / views.depth_range_m


def _nearest_keys(
    pix: torch.Tensor, z_n: torch.Tensor, faces: torch.Tensor, res: int, max_candidates: int
) -> torch.Tensor:
    """(N * res * res,) int64 per pixel: float32 depth bits above the nearest face's index
    (ties go to the lower index), or `_NO_HIT`. `pix` (N, V, 2), `z_n` (N, V), `faces` (F, 3)."""
    keys = torch.full((pix.shape[0] * res * res,), _NO_HIT, dtype=torch.int64, device=pix.device)
    corners = _corner_table(pix, z_n, faces)
    lo, hi, counts = _pixel_boxes(corners, res)
    pairs = torch.nonzero(counts.reshape(-1)).squeeze(1)
    # Only (view, face) pairs with pixels go on; one row per pair keeps the per-candidate
    # gathers down to two.
    table = corners.reshape(-1, 9).index_select(0, pairs)
    counts = counts.reshape(-1).index_select(0, pairs)
    face_count = faces.shape[0]
    lo_p, hi_p = lo.reshape(-1, 2).index_select(0, pairs), hi.reshape(-1, 2).index_select(0, pairs)
    first_pixel = (pairs // face_count * res + lo_p[:, 1]) * res + lo_p[:, 0]
    layout = torch.stack([lo_p[:, 0], lo_p[:, 1], hi_p[:, 0] - lo_p[:, 0] + 1, first_pixel,
                          pairs % face_count], dim=1)  # (P, 5) int64
    for run in _chunks(counts, max_candidates):
        _scatter_run(keys, table[run], layout[run], counts[run], res)
    return keys


def _corner_table(pix: torch.Tensor, z_n: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """(N, F, 9) per view and face: corner columns (3), rows (3) and normalised depths (3)."""
    n_views, n_vertices = z_n.shape
    per_vertex = torch.cat([pix, z_n[..., None]], dim=-1).reshape(-1, 3)  # (N * V, 3)
    offsets = torch.arange(n_views, device=faces.device) * n_vertices
    rows = (offsets[:, None, None] + faces[None]).reshape(-1)
    # (N, F, corner, coordinate) to (N, F, coordinate, corner): columns, rows, then depths.
    table = per_vertex.index_select(0, rows).reshape(n_views, -1, 3, 3).transpose(2, 3)
    return table.reshape(n_views, -1, 9)


def _pixel_boxes(
    corners: torch.Tensor, res: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per (view, face) of `corners` (N, F, 9): the first and last pixel centre (column, row)
    inside its bounding box, clipped to the image, (N, F, 2) int64 each, and the box's pixel
    count (N, F), 0 for faces whose projection has no area."""
    xy = corners[..., :6].reshape(*corners.shape[:-1], 2, 3)  # (N, F, 2, 3)
    # Clamp before the integer cast so far-off vertices cannot overflow it; a box wholly off
    # the image ends up with hi < lo and so no pixels.
    lo = xy.amin(dim=-1).clamp(-1.0, float(res)).ceil().long().clamp(min=0)
    hi = xy.amax(dim=-1).clamp(-1.0, float(res)).floor().long().clamp(max=res - 1)
    span = (hi - lo + 1).clamp(min=0)
    counts = span[..., 0] * span[..., 1] * (_twice_area(xy[..., 0, :], xy[..., 1, :]) != 0)
    return lo, hi, counts


def _twice_area(cols: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """Signed doubled area (...,) of projected triangles with corner `cols`, `rows` (..., 3)."""
    du_c, du_r = cols[..., 1] - cols[..., 0], rows[..., 1] - rows[..., 0]
    dv_c, dv_r = cols[..., 2] - cols[..., 0], rows[..., 2] - rows[..., 0]
    return du_c * dv_r - du_r * dv_c


def _chunks(counts: torch.Tensor, max_candidates: int) -> list[slice]:
    """Consecutive runs of `counts` (P,) summing to about `max_candidates` at most (a run holds
    at least one entry)."""
    if counts.numel() == 0:
        return []
    ends = torch.cumsum(counts, 0)
    # One host sync for all the split points.
    bucket = ((ends - counts) // max(max_candidates, 1)).cpu().numpy()
    starts = np.flatnonzero(np.diff(bucket, prepend=-1))
    bounds = [*starts.tolist(), len(bucket)]
    return [slice(s, e) for s, e in zip(bounds[:-1], bounds[1:], strict=True)]


def _scatter_run(
    keys: torch.Tensor, table: torch.Tensor, layout: torch.Tensor, counts: torch.Tensor, res: int
) -> None:
    """Min-reduces into `keys` the hits of (view, face) pairs given by their `table` rows
    (P, 9) (see `_corner_table`), `layout` rows (P, 5) (box's first column, first row, width,
    flat first pixel, face) and box pixel `counts` (P,)."""
    owner = torch.repeat_interleave(torch.arange(len(counts), device=keys.device), counts)
    first = torch.cumsum(counts, 0) - counts
    local = torch.arange(owner.numel(), device=keys.device) - first.index_select(0, owner)
    box = layout.index_select(0, owner)
    d_col, d_row = local % box[:, 2], local // box[:, 2]
    tri = table.index_select(0, owner)
    point = torch.stack([box[:, 0] + d_col, box[:, 1] + d_row], dim=-1).to(tri.dtype)
    weights = _edge_weights(tri[:, :6].reshape(-1, 2, 3).transpose(1, 2), point)
    hit = torch.nonzero(_covered(weights)).squeeze(1)
    weights = weights.index_select(0, hit)
    depth = (weights * tri.index_select(0, hit)[:, 6:]).sum(-1) / weights.sum(-1)
    # The ray cast starts on the near plane: nothing in front of it is seen.
    front = depth >= 0
    hit, depth = hit[front], depth[front]
    depth_bits = depth.to(torch.float32).abs().view(torch.int32).long()
    flat = box[hit, 3] + d_row[hit] * res + d_col[hit]
    keys.scatter_reduce_(0, flat, (depth_bits << _FACE_BITS) | box[hit, 4], "amin")


def _edge_weights(tri: torch.Tensor, point: torch.Tensor) -> torch.Tensor:
    """(M, 3) unnormalised barycentric weights of `point` (M, 2) in triangles `tri` (M, 3, 2):
    each the signed doubled area of the point and the opposite edge."""
    rel = tri - point[:, None, :]
    a, b, c = rel.unbind(1)
    # An edge (u, v) is always evaluated as cross(u - p, v - p): its neighbour, which walks it
    # as (v, u), gets the exact negative, so no pixel centre slips between two faces.
    return torch.stack([_cross(b, c), _cross(c, a), _cross(a, b)], dim=-1)


def _cross(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    return u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]


def _covered(weights: torch.Tensor) -> torch.Tensor:
    """(M,) True where all weights (M, 3) share a sign, edges included: either winding."""
    return (weights >= 0).all(-1) | (weights <= 0).all(-1)


def _pixel_colors(
    pix: torch.Tensor,
    faces: torch.Tensor,
    colors: torch.Tensor,
    face_of_pixel: torch.Tensor,
    valid: torch.Tensor,
    res: int,
) -> torch.Tensor:
    """(N * res * res, 3) uint8: the vertex `colors` (V, 3) of each pixel's face
    (`face_of_pixel`, (N * res * res,)) interpolated at its centre, 0 where not `valid`."""
    flat = torch.nonzero(valid).squeeze(1)
    view, row, col = flat // (res * res), (flat // res) % res, flat % res
    corner_ids = faces.index_select(0, face_of_pixel.index_select(0, flat))  # (P, 3)
    tri = pix[view[:, None], corner_ids]  # (P, 3, 2)
    weights = _edge_weights(tri, torch.stack([col, row], -1).to(tri.dtype))
    total = weights.sum(-1, keepdim=True)
    bary = weights / torch.where(total == 0, 1.0, total)
    rgb = (bary[..., None] * colors[corner_ids]).sum(1).clamp(0.0, 255.0)
    out = torch.zeros((valid.numel(), 3), dtype=torch.uint8, device=valid.device)
    out[flat] = rgb.to(torch.uint8)
    return out
