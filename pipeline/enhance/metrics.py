"""Mesh and depth quality figures: CloudCompare-style C2M distances, normal error, depth RMSE."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from pipeline.geometry.mesh import TriangleMesh, face_normals, vertex_normals
from pipeline.reconstruct.quality import signed_distances_m


def _closest(reference: TriangleMesh, points_m: NDArray[np.float64]):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor.from_numpy(reference.vertices_m.astype(np.float32)),
        o3d.core.Tensor.from_numpy(reference.faces.astype(np.uint32)),
    )
    out = scene.compute_closest_points(o3d.core.Tensor.from_numpy(points_m.astype(np.float32)))
    return out["points"].numpy().astype(np.float64), out["primitive_ids"].numpy().astype(np.int64)


def signed_c2m(points_m: NDArray[np.float64], reference: TriangleMesh) -> NDArray[np.float64]:
    """(P,) signed distance of points to a mesh, metres; the sign from the nearest face's normal.

    This is what CloudCompare's C2M reports with signed distances on.
    """
    return signed_distances_m(points_m, reference)


def c2m_summary(result: TriangleMesh, truth: TriangleMesh) -> dict[str, float]:
    """Signed mean / std / RMS of result vertices to the truth, and the reverse (truth→result)
    mean and RMS, all in millimetres."""
    s = signed_c2m(result.vertices_m, truth)
    r = np.abs(signed_c2m(truth.vertices_m, result))
    return {
        "c2m_mean_mm": float(s.mean() * 1e3),
        "c2m_std_mm": float(s.std() * 1e3),
        "c2m_rms_mm": float(np.sqrt(np.mean(s**2)) * 1e3),
        "reverse_mean_mm": float(r.mean() * 1e3),
        "reverse_rms_mm": float(np.sqrt(np.mean(r**2)) * 1e3),
    }


def normal_error_deg(result: TriangleMesh, truth: TriangleMesh) -> float:
    """Mean angle between each result vertex's normal and the truth's face normal nearest it."""
    _, prim = _closest(truth, result.vertices_m)
    n_true = face_normals(truth.vertices_m, truth.faces)[prim]
    n_res = vertex_normals(result.vertices_m, result.faces).astype(np.float64)
    cos = np.clip(np.sum(n_true * n_res, axis=1), -1.0, 1.0)
    return float(np.degrees(np.arccos(cos)).mean())


def depth_edge_band(depth_n: NDArray, valid: NDArray[np.bool_], jump: float, width_px: int = 3):
    """(H, W) mask of pixels within `width_px` of a depth edge (jump > `jump`) or the silhouette."""
    import cv2

    d = np.where(valid, depth_n, 1.0).astype(np.float32)
    gx = np.abs(np.diff(d, axis=1, append=d[:, -1:]))
    gy = np.abs(np.diff(d, axis=0, append=d[-1:, :]))
    edge = ((gx > jump) | (gy > jump)).astype(np.uint8)
    kernel = np.ones((2 * width_px + 1, 2 * width_px + 1), np.uint8)
    return cv2.dilate(edge, kernel).astype(bool) & valid


def correction_calibration(
    pred_n: NDArray, base_n: NDArray, clean_n: NDArray, mask: NDArray[np.bool_]
) -> dict[str, float]:
    """How a predicted depth correction (pred - base) matches the true one (clean - base)
    over `mask`: the least-squares gain of true on predicted (1: calibrated, below 1:
    over-confident), their correlation, and the mean of (pred - clean) in thousandths of the
    depth range (negative: the prediction lies nearer the camera than the truth)."""
    true = (clean_n - base_n)[mask].astype(np.float64)
    predicted = (pred_n - base_n)[mask].astype(np.float64)
    return {
        "gain": float(np.sum(true * predicted) / np.sum(predicted**2)),
        "correlation": float(np.corrcoef(true, predicted)[0, 1]),
        "bias_permille": 1e3 * float(np.mean(predicted - true)),
    }
