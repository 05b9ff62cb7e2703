"""Optional depth-based refinement: point-to-plane ICP between the cameras' depth clouds.

Real sensors' factory ``color_from_depth`` is off by a little; ChArUco fixes the colour
cameras, this moves each depth camera so its cloud meets the others'. Correspondences are
searched frame by frame (the subject may move between frames) and all frames feed one solve
per camera. The reference camera stays put.

By default only the depth cameras' positions move: the offsets real sensors have are mostly
translations of a few millimetres, and on the small overlaps of a ring of cameras a rotation
about the overlap is barely constrained (a fraction of a degree there swings the camera centre
by centimetres), while the ChArUco fit already gives rotations to about 0.01 degrees.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from pipeline.calibration.config import CalibrationConfig
from pipeline.calibration.transforms import from_rotvec, rotation_angle_deg, transform_points
from pipeline.capture import Intrinsics

Matrix = NDArray[np.float64]
_NORMAL_AGREEMENT = np.cos(np.radians(30.0))
Cloud = tuple[Matrix, Matrix]
"""(points (N, 3), unit normals (N, 3)), metres, in a camera's depth frame."""


def depth_cloud(depth_m: NDArray[np.floating], intrinsics: Intrinsics, voxel_size_m: float,
                stride: int = 2) -> Cloud:
    """A thinned cloud with normals (facing the camera) from one depth image."""
    import open3d as o3d

    rows, cols = np.nonzero(np.asarray(depth_m)[::stride, ::stride] > 0)
    rows, cols = rows * stride, cols * stride
    z = np.asarray(depth_m, dtype=np.float64)[rows, cols]
    pixels = np.column_stack([cols, rows]).astype(np.float64)
    if intrinsics.has_distortion and len(pixels):
        pixels = np.asarray(cv2.undistortPoints(
            pixels.reshape(-1, 1, 2), intrinsics.matrix(), intrinsics.distortion_coeffs(),
            P=intrinsics.matrix()), np.float64).reshape(-1, 2)
    points = np.column_stack([(pixels[:, 0] - intrinsics.cx) / intrinsics.fx * z,
                              (pixels[:, 1] - intrinsics.cy) / intrinsics.fy * z, z])
    if len(points) < 10:
        return np.zeros((0, 3)), np.zeros((0, 3))
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud = cloud.voxel_down_sample(voxel_size_m)
    # Nearest neighbours, not a radius: seen obliquely, a surface's samples spread apart.
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=16))
    cloud.orient_normals_towards_camera_location(np.zeros(3))
    return np.asarray(cloud.points).copy(), np.asarray(cloud.normals).copy()


def _pairs(world: Mapping[str, Mapping[int, Cloud]], trees: Mapping[tuple[str, int], cKDTree],
           max_distance_m: float) -> list[tuple[str, str, Matrix, Matrix, Matrix]]:
    """(camera a, camera b, points of a, matched points of b, normals of b) in the world, for
    every ordered camera pair and frame, on surfaces facing the same way."""
    out = []
    for cam_a, frames in world.items():
        for frame, (points, normals) in frames.items():
            for cam_b in world:
                if cam_b == cam_a or (cam_b, frame) not in trees or len(points) == 0:
                    continue
                dist, index = trees[(cam_b, frame)].query(points,
                                                          distance_upper_bound=max_distance_m)
                hit = np.flatnonzero(np.isfinite(dist))
                other_points, other_normals = world[cam_b][frame]
                # Pairs on differently facing surfaces (across a cube's edge, the two sides
                # of a thin board) are not the same surface.
                agree = np.einsum("ni,ni->n", normals[hit],
                                  other_normals[index[hit]]) > _NORMAL_AGREEMENT
                hit = hit[agree]
                if len(hit):
                    out.append((cam_a, cam_b, points[hit], other_points[index[hit]],
                                other_normals[index[hit]]))
    return out


def _joint_step(pairs: list[tuple[str, str, Matrix, Matrix, Matrix]], free: list[str],
                pivots: Mapping[str, Matrix], with_rotation: bool) -> dict[str, Matrix]:
    """World increments of the free cameras minimising all point-to-plane residuals at once.

    Residual n . (p_a - q_b); moving camera a by (w, t) about its pivot changes it by
    (p_a - pivot_a) x n . w + n . t, moving camera b by the opposite for q_b.
    """
    column = {c: 6 * i for i, c in enumerate(free)}
    normal_matrix = np.zeros((6 * len(free), 6 * len(free)))
    rhs = np.zeros(6 * len(free))
    for cam_a, cam_b, p, q, n in pairs:
        residual = np.einsum("ni,ni->n", p - q, n)
        blocks = []
        for camera_id, points, sign in ((cam_a, p, 1.0), (cam_b, q, -1.0)):
            if camera_id in column:
                jac = sign * np.column_stack([np.cross(points - pivots[camera_id], n), n])
                blocks.append((column[camera_id], jac))
        for col_i, jac_i in blocks:
            rhs[col_i:col_i + 6] -= jac_i.T @ residual
            for col_j, jac_j in blocks:
                normal_matrix[col_i:col_i + 6, col_j:col_j + 6] += jac_i.T @ jac_j
    keep = np.ones(len(rhs), dtype=bool)
    if not with_rotation:
        keep[np.arange(len(rhs)) % 6 < 3] = False
    step = np.zeros(len(rhs))
    reduced = normal_matrix[np.ix_(keep, keep)]
    values, vectors = np.linalg.eigh(reduced)
    # Directions the clouds do not constrain (a lone plane slides) are left alone.
    usable = values > 1e-6 * max(values.max(), 1e-30)
    step[keep] = vectors[:, usable] @ ((vectors[:, usable].T @ rhs[keep]) / values[usable])
    increments = {}
    for camera_id, col in column.items():
        increment = from_rotvec(step[col:col + 3], step[col + 3:col + 6])
        increment[:3, 3] += pivots[camera_id] - increment[:3, :3] @ pivots[camera_id]
        increments[camera_id] = increment
    return increments


def _world_clouds(clouds: Mapping[str, Mapping[int, Cloud]], poses: Mapping[str, Matrix]
                  ) -> dict[str, dict[int, Cloud]]:
    return {c: {f: (transform_points(poses[c], p), n @ poses[c][:3, :3].T)
                for f, (p, n) in frames.items() if len(p)} for c, frames in clouds.items()}


def refine_with_depth(clouds: Mapping[str, Mapping[int, Cloud]],
                      world_from_depth: Mapping[str, Matrix], reference: str,
                      config: CalibrationConfig, iterations: int = 30
                      ) -> tuple[dict[str, Matrix], dict[str, Any]]:
    """ICP-refined ``world_from_depth`` and a report of each camera's correction.

    clouds: per camera, per frame, the depth cloud in that camera's depth frame. All cameras
    are solved together (each pulled by every camera it overlaps, the reference fixed), so
    a misplaced neighbour does not drag the others. Corrections beyond the configured limits
    are refused and reported as warnings.
    """
    poses = {c: np.asarray(p, dtype=float).copy() for c, p in world_from_depth.items()}
    free = [c for c in poses if c != reference and c in clouds]
    matches: dict[str, int] = dict.fromkeys(poses, 0)
    for _ in range(iterations):
        world = _world_clouds(clouds, poses)
        trees = {(c, f): cKDTree(p) for c, frames in world.items() for f, (p, _) in frames.items()}
        pairs = _pairs(world, trees, config.icp_max_distance_m)
        matches = dict.fromkeys(poses, 0)
        for cam_a, _, p, _, _ in pairs:
            matches[cam_a] += len(p)
        if sum(matches.values()) < 50 or not free:
            break
        pivots = {c: np.concatenate([p for p, _ in world[c].values()]).mean(axis=0)
                  for c in free if world.get(c)}
        increments = _joint_step(pairs, [c for c in free if c in pivots], pivots,
                                 config.icp_rotation)
        for camera_id, increment in increments.items():
            poses[camera_id] = increment @ poses[camera_id]
        largest = max((np.linalg.norm(i[:3, 3]) for i in increments.values()), default=0.0)
        if largest < 1e-6:
            break
    return _limited(world_from_depth, poses, matches, config)


def _limited(start_poses: Mapping[str, Matrix], poses: Mapping[str, Matrix],
             matches: Mapping[str, int], config: CalibrationConfig
             ) -> tuple[dict[str, Matrix], dict[str, Any]]:
    out, corrections, warnings = {}, {}, []
    for camera_id, pose in poses.items():
        start = np.asarray(start_poses[camera_id], dtype=float)
        moved_m = float(np.linalg.norm(pose[:3, 3] - start[:3, 3]))
        turned_deg = rotation_angle_deg(pose[:3, :3] @ start[:3, :3].T)
        corrections[camera_id] = {"moved_mm": moved_m * 1000.0, "turned_deg": turned_deg,
                                  "correspondences": matches.get(camera_id, 0)}
        if moved_m > config.icp_max_correction_m or turned_deg > config.icp_max_correction_deg:
            warnings.append(f"depth ICP refused for camera {camera_id}: it would move "
                            f"{moved_m * 1000:.1f} mm / {turned_deg:.2f} deg, beyond the limits")
            out[camera_id] = start
        else:
            out[camera_id] = pose
    return out, {"corrections": corrections, "warnings": warnings}
