"""The mesh update in torch on a device (`steps` chooses this or `steps_numpy`): normals,
lookups, averaging, smoothing and the fold check stay on the device. float64 throughout, so
both implementations agree to rounding."""

from __future__ import annotations

import math

import numpy as np
import torch
from numpy.typing import NDArray

from pipeline.enhance.device import csr_on_device, on_device
from pipeline.enhance.mesh_torch import face_normals, vertex_normals
from pipeline.enhance.render.camera import DepthRenders
from pipeline.enhance.render.rasterize import project_px
from pipeline.enhance.update.steps_common import UpdateConfig, ViewSteps
from pipeline.geometry.mesh import TriangleMesh
from pipeline.geometry.smoothing import mean_operator


def view_steps(
    mesh: TriangleMesh,
    renders: DepthRenders,
    enhanced_depth_n: NDArray[np.float32],
    config: UpdateConfig,
    device: str,
) -> ViewSteps:
    """`steps.view_steps` on `device`; the result in numpy, as `steps_numpy`'s."""
    views = renders.views
    vertices_m = on_device(mesh.vertices_m, device)
    faces = on_device(mesh.faces.astype(np.int64), device)
    # scipy builds the operator on the host, where `ViewSteps` carries it for the smoothing
    # of the unseen vertices.
    mean_op = mean_operator(mesh.faces, mesh.vertex_count)
    normals = smoothed_normals(vertices_m, faces, csr_on_device(mean_op, device),
                               config.normal_smoothing)
    forwards = on_device(np.asarray(views.forwards, np.float64), device)
    pix, depth_all_n = project_px(vertices_m, views)
    cols_all, rows_all = pix[..., 0], pix[..., 1]
    cos_all = -(forwards @ normals.T)
    res = views.resolution
    # Only vertices inside a view and facing it can be seen there: the lookups run on those
    # (view, vertex) pairs alone, all views at once.
    view, at = torch.nonzero(
        (cols_all >= 0) & (cols_all <= res - 1) & (rows_all >= 0) & (rows_all <= res - 1)
        & (cos_all > config.min_cos), as_tuple=True)
    cos, cols, rows = cos_all[view, at], cols_all[view, at], rows_all[view, at]
    depth_n = depth_all_n[view, at]
    own_n = on_device(renders.depth_n, device)
    enhanced_n = on_device(enhanced_depth_n, device)
    valid = on_device(renders.valid, device)
    pixels = Pixels(view, cols, rows, res)
    seen_depth_n, seen_ok = bilinear(own_n, valid, pixels)
    tan = torch.sqrt(torch.clamp(1.0 - cos**2, min=0.0)) / torch.clamp(cos, min=1e-3)
    tol_n = config.tolerance_px * (1.0 + tan) / res
    visible = seen_ok & (torch.abs(seen_depth_n - depth_n) < tol_n)
    _, target_ok = bilinear(enhanced_n, valid, pixels, max_spread=3.0 * tol_n)
    step_m = bilinear(enhanced_n - own_n, valid, pixels)[0] * views.depth_range_m
    cap_m = config.max_step_fraction * views.half_extent_m
    # A step beyond the cap means the lookup landed on another surface: not this view's.
    visible &= target_ok & (torch.abs(step_m) < cap_m)
    steps_m = torch.zeros_like(cos_all)
    weights = torch.zeros_like(cos_all)
    steps_m[view, at] = torch.where(visible, step_m, 0.0)
    weights[view, at] = torch.where(visible, cos**2, 0.0)
    return ViewSteps(_numpy(steps_m), _numpy(weights), np.asarray(views.forwards, np.float64),
                     _numpy(normals), cap_m, mean_op)


def apply_view_steps(
    mesh: TriangleMesh,
    steps: ViewSteps,
    config: UpdateConfig,
    vertex_gain: NDArray[np.float64] | None,
    device: str,
) -> tuple[TriangleMesh, NDArray[np.bool_]]:
    """`steps.apply_view_steps` on `device`; the mesh and (V,) seen mask in numpy."""
    vertices_m = on_device(mesh.vertices_m, device)
    weights = on_device(steps.weights, device)
    weight = weights.sum(dim=0)
    shift_m = (weights * on_device(steps.steps_m, device)).T @ on_device(steps.forwards, device)
    seen = weight > 0
    shift_m = shift_m / torch.where(seen, weight, 1.0)[:, None]
    if vertex_gain is not None:
        shift_m = shift_m * on_device(vertex_gain, device)[:, None]
    length_m = torch.linalg.vector_norm(shift_m, dim=1)
    scale = torch.clamp(steps.cap_m / torch.clamp(length_m, min=1e-30), max=1.0)
    shift_m = shift_m * scale[:, None]
    seen_host = _numpy(seen)
    # The unseen rows alone, sliced on the host where `seen` has to go anyway: a small share
    # of the operator to carry to the device.
    unseen = np.flatnonzero(~seen_host)
    unseen_op = csr_on_device(steps.mean_op[unseen], device) if len(unseen) else None
    unseen_at = on_device(unseen, device)
    moved_m = vertices_m + smooth_unseen(shift_m, unseen_at, unseen_op,
                                         config.unseen_iterations)
    faces = on_device(mesh.faces.astype(np.int64), device)
    return mesh.with_vertices(_numpy(unfolded(vertices_m, moved_m, faces))), seen_host


class Pixels:
    """Where (P,) samples fall in a stack of (K, H, W) square images of side `resolution`:
    each sample's view and continuous column and row."""

    def __init__(self, view: torch.Tensor, cols: torch.Tensor, rows: torch.Tensor,
                 resolution: int):
        self.cols, self.rows, self.resolution = cols, rows, resolution
        self.view_offset = view * resolution * resolution


def bilinear(
    image: torch.Tensor, valid: torch.Tensor, pixels: Pixels,
    max_spread: float | torch.Tensor = math.inf,
) -> tuple[torch.Tensor, torch.Tensor]:
    """`steps_numpy.bilinear` over a (K, H, W) stack of float32 images with their (K, H, W) valid
    masks at (P,) `pixels`: float64 values and their validity."""
    side = pixels.resolution
    flat, flat_valid = image.reshape(-1), valid.reshape(-1)
    c0 = torch.clamp(torch.floor(pixels.cols).long(), 0, side - 2)
    r0 = torch.clamp(torch.floor(pixels.rows).long(), 0, side - 2)
    fc = torch.clamp(pixels.cols - c0, 0.0, 1.0)
    fr = torch.clamp(pixels.rows - r0, 0.0, 1.0)
    corner = (pixels.view_offset + r0 * side + c0)[:, None] + torch.tensor(
        [0, 1, side, side + 1], device=c0.device)
    q = flat[corner]
    ok = flat_valid[corner].all(dim=1)
    # The spread in the images' float32, as numpy takes it.
    ok &= (q.amax(dim=1) - q.amin(dim=1)).double() < max_spread
    q = q.double()
    bil = ((q[:, 0] * (1 - fc) + q[:, 1] * fc) * (1 - fr)
           + (q[:, 2] * (1 - fc) + q[:, 3] * fc) * fr)
    # torch.round, like np.rint, rounds halves to even.
    nearest = (pixels.view_offset + torch.clamp(torch.round(pixels.rows).long(), 0, side - 1)
               * side + torch.clamp(torch.round(pixels.cols).long(), 0, side - 1))
    return torch.where(ok, bil, flat[nearest].double()), ok | flat_valid[nearest]


def smoothed_normals(vertices_m: torch.Tensor, faces: torch.Tensor, mean_op: torch.Tensor,
                     passes: int) -> torch.Tensor:
    """(V, 3) float64 unit vertex normals (float32-rounded, as `pipeline.geometry.mesh`'s) averaged
    over the neighbours `passes` times by the (V, V) `mean_op`."""
    normals = vertex_normals(vertices_m, faces).double()
    for _ in range(passes):
        normals = mean_op @ normals
        normals = normals / torch.clamp(torch.linalg.vector_norm(normals, dim=1, keepdim=True),
                                        min=1e-12)
    return normals


def smooth_unseen(field: torch.Tensor, unseen: torch.Tensor, unseen_op: torch.Tensor | None,
                  iterations: int) -> torch.Tensor:
    """`steps_numpy.smooth_unseen` of a (V, 3) field, given the (U,) unseen vertices and their
    (U, V) rows of the mean operator (None when there are none)."""
    if unseen_op is None:
        return field
    out = field.clone()
    for _ in range(iterations):
        out[unseen] = unseen_op @ out
    return out


def unfolded(before_m: torch.Tensor, after_m: torch.Tensor, faces: torch.Tensor
             ) -> torch.Tensor:
    """`steps_numpy.unfolded` of (V, 3) vertices and (F, 3) int64 faces."""
    normals_before = face_normals(before_m, faces)
    out = after_m.clone()
    check = torch.arange(len(faces), device=faces.device)
    put_back = torch.zeros(len(out), dtype=torch.bool, device=out.device)
    # As in `steps_numpy`: each round puts back at least one moved vertex, and only the faces at the
    # vertices put back are checked again.
    while len(check):
        turned = torch.sum(face_normals(out, faces[check]) * normals_before[check], dim=1) < 0
        corners = faces[check[turned]].reshape(-1)
        out[corners] = before_m[corners]
        put_back.zero_()
        put_back[corners] = True
        check = torch.nonzero(put_back[faces[:, 0]] | put_back[faces[:, 1]]
                              | put_back[faces[:, 2]]).reshape(-1)
    return out


def _numpy(tensor: torch.Tensor) -> NDArray:
    return tensor.cpu().numpy()
