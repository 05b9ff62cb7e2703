"""The mesh update in numpy and scipy on the host: each view's step for each vertex, then
their weighted average applied (`steps` chooses this or `steps_torch`)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from pipeline.enhance.render.camera import DepthRenders, project
from pipeline.enhance.update.steps_common import UpdateConfig, ViewSteps
from pipeline.geometry.mesh import TriangleMesh, face_normals, vertex_normals
from pipeline.geometry.repair import faces_at
from pipeline.geometry.smoothing import mean_operator


def view_steps(
    mesh: TriangleMesh,
    renders: DepthRenders,
    enhanced_depth_n: NDArray[np.float32],
    config: UpdateConfig,
) -> ViewSteps:
    """`steps.view_steps` (shapes already checked)."""
    views = renders.views
    v = mesh.vertices_m
    mean_op = mean_operator(mesh.faces, mesh.vertex_count)
    normals = vertex_normals(v, mesh.faces).astype(np.float64)
    for _ in range(config.normal_smoothing):
        normals = mean_op @ normals
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    pix, depth_n = project(v, views)
    res = views.resolution
    cap = config.max_step_fraction * views.half_extent_m
    steps = np.zeros((views.count, len(v)))
    weights = np.zeros((views.count, len(v)))
    for k in range(views.count):
        cos_all = -normals @ views.forwards[k]
        cols_all, rows_all = pix[k, :, 0], pix[k, :, 1]
        # Only vertices inside the view and facing it can be seen: the lookups run on them
        # alone.
        at = np.flatnonzero((cols_all >= 0) & (cols_all <= res - 1) & (rows_all >= 0)
                            & (rows_all <= res - 1) & (cos_all > config.min_cos))
        cos, cols, rows = cos_all[at], cols_all[at], rows_all[at]
        seen_depth, seen_ok = bilinear(renders.depth_n[k], renders.valid[k], cols, rows)
        tan = np.sqrt(np.maximum(1.0 - cos**2, 0.0)) / np.maximum(cos, 1e-3)
        tol = config.tolerance_px * (1.0 + tan) / res
        visible = seen_ok & (np.abs(seen_depth - depth_n[k, at]) < tol)
        _, target_ok = bilinear(
            enhanced_depth_n[k], renders.valid[k], cols, rows, max_spread=3.0 * tol
        )
        change = enhanced_depth_n[k] - renders.depth_n[k]
        step = bilinear(change, renders.valid[k], cols, rows)[0] * views.depth_range_m
        # A step beyond the cap means the lookup landed on another surface: not this view's.
        visible &= target_ok & (np.abs(step) < cap)
        steps[k, at] = np.where(visible, step, 0.0)
        weights[k, at] = np.where(visible, cos**2, 0.0)
    return ViewSteps(steps, weights, np.asarray(views.forwards, np.float64), normals, cap,
                     mean_op)


def apply_view_steps(
    mesh: TriangleMesh,
    steps: ViewSteps,
    config: UpdateConfig,
    vertex_gain: NDArray[np.float64] | None,
) -> tuple[TriangleMesh, NDArray[np.bool_]]:
    """`steps.apply_view_steps`."""
    v = mesh.vertices_m
    weight = steps.weights.sum(axis=0)
    shift = (steps.weights * steps.steps_m).T @ steps.forwards
    seen = weight > 0
    shift[seen] /= weight[seen, None]
    if vertex_gain is not None:
        shift *= vertex_gain[:, None]
    length = np.linalg.norm(shift, axis=1)
    shift *= np.minimum(1.0, steps.cap_m / np.maximum(length, 1e-30))[:, None]
    moved = v + smooth_unseen(shift, seen, steps.mean_op, config.unseen_iterations)
    return mesh.with_vertices(unfolded(v, moved, mesh.faces)), seen


def bilinear(
    image: NDArray[np.float32],
    valid: NDArray[np.bool_],
    cols: NDArray,
    rows: NDArray,
    max_spread: float | NDArray = np.inf,
):
    """Bilinear lookup where the four neighbours are valid and on one surface (spread below
    `max_spread`), nearest otherwise; returns values and whether they are valid."""
    h, w = image.shape
    c0 = np.clip(np.floor(cols).astype(np.int64), 0, w - 2)
    r0 = np.clip(np.floor(rows).astype(np.int64), 0, h - 2)
    fc = np.clip(cols - c0, 0.0, 1.0)
    fr = np.clip(rows - r0, 0.0, 1.0)
    q = [image[r0, c0], image[r0, c0 + 1], image[r0 + 1, c0], image[r0 + 1, c0 + 1]]
    ok = valid[r0, c0] & valid[r0, c0 + 1] & valid[r0 + 1, c0] & valid[r0 + 1, c0 + 1]
    ok &= (np.maximum.reduce(q) - np.minimum.reduce(q)) < max_spread
    bil = (q[0] * (1 - fc) + q[1] * fc) * (1 - fr) + (q[2] * (1 - fc) + q[3] * fc) * fr
    nc = np.clip(np.rint(cols).astype(np.int64), 0, w - 1)
    nr = np.clip(np.rint(rows).astype(np.int64), 0, h - 1)
    return np.where(ok, bil, image[nr, nc]), np.where(ok, True, valid[nr, nc])


def unfolded(before_m: NDArray, after_m: NDArray, faces: NDArray[np.int32]) -> NDArray:
    """(V, 3) `after_m` with the corners of every face the move turned over (normal more than
    90 degrees from its own before) put back where they were, until none is: vertices move
    independently, and a fold is the one defect the connectivity cannot show."""
    normals_before = face_normals(before_m, faces)
    out = after_m.copy()
    check = np.arange(len(faces))
    # Each round puts back at least one moved vertex, so it ends at the latest at before;
    # only the faces at the vertices put back can change, so only they are checked again.
    while len(check):
        turned = np.sum(face_normals(out, faces[check]) * normals_before[check], axis=1) < 0
        corners = faces[check[turned]].ravel()
        out[corners] = before_m[corners]
        put_back = np.zeros(len(out), dtype=bool)
        put_back[corners] = True
        check = np.nonzero(faces_at(faces, put_back))[0]
    return out


def smooth_unseen(v: NDArray, seen: NDArray[np.bool_], mean_op, iterations: int) -> NDArray:
    """Jacobi smoothing of a (V, 3) per-vertex field over the unseen vertices, the seen ones
    fixed."""
    out = v.copy()
    unseen = ~seen
    if not unseen.any():
        return out
    rows = mean_op[unseen]  # only the unseen rows change
    for _ in range(iterations):
        out[unseen] = rows @ out
    return out
