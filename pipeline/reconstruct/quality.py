"""Quality figures of a reconstruction against a ground-truth mesh, and, where there is no
ground truth (real captures), against the raw depth it was made from (`depth_agreement`).

Distances are measured between area-uniform surface samples and the other mesh, with
open3d's ray-casting scene (exact closest points on triangles). Signs come from the normal
of the closest triangle (positive outside), which works for open meshes too, where a
parity-based inside test would not.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from pipeline.capture import CameraInfo
from pipeline.geometry.mesh import TriangleMesh, face_normals
from pipeline.reconstruct.registration import invert_rigid, project, transform

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class MetricsConfig:
    """How the figures are sampled."""

    sample_count: int = 200_000
    """Area-uniform samples drawn on each mesh."""
    coverage_threshold_m: float = 0.005
    """A ground-truth sample is covered when the result lies within this distance, metres."""
    min_view_cos: float = 0.1
    """A camera sees a ground-truth sample only when the cosine between the view ray and the
    surface normal is at least this (about 84 degrees: beyond, a time-of-flight sensor gets
    no return, so no method could reconstruct it)."""
    min_range_m: float = 0.25
    """Nearest distance a camera sees, metres."""
    max_range_m: float = 5.5
    """Farthest distance a camera sees, metres."""
    occlusion_tolerance_m: float = 0.001
    """A sample is unoccluded when the first hit along the camera's ray to it is no nearer
    than its distance minus this, metres."""
    seed: int = 0
    """Seed of the surface sampling."""

    def __post_init__(self) -> None:
        if self.sample_count < 1 or not self.coverage_threshold_m > 0:
            raise ValueError("metrics: sample_count >= 1 and coverage_threshold_m > 0 needed")


def sample_surface(mesh: TriangleMesh, count: int, seed: int = 0
                   ) -> tuple[FloatArray, FloatArray]:
    """(count, 3) area-uniform points on the mesh and (count, 3) their face normals."""
    vertices = np.asarray(mesh.vertices_m, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if not area.sum() > 0:
        raise ValueError("mesh: has no area to sample")
    rng = np.random.default_rng(seed)
    face = rng.choice(len(faces), size=count, p=area / area.sum())
    u, v = rng.random(count), rng.random(count)
    flip = u + v > 1
    u, v = np.where(flip, 1 - u, u), np.where(flip, 1 - v, v)
    t = tri[face]
    points = t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])
    return points, face_normals(vertices, faces.astype(np.int32))[face]


class _Scene:
    """A ray-casting scene of one mesh."""

    def __init__(self, mesh: TriangleMesh) -> None:
        import open3d as o3d

        self._o3d = o3d
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(
            o3d.core.Tensor.from_numpy(np.ascontiguousarray(mesh.vertices_m, dtype=np.float32)),
            o3d.core.Tensor.from_numpy(np.ascontiguousarray(mesh.faces, dtype=np.uint32)))
        self.normals = face_normals(np.asarray(mesh.vertices_m, dtype=np.float64),
                                    np.asarray(mesh.faces, dtype=np.int32))

    def closest(self, points: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Signed distances (positive outside), closest points and their face normals."""
        query = self._o3d.core.Tensor.from_numpy(np.ascontiguousarray(points, np.float32))
        answer = self.scene.compute_closest_points(query)
        closest = answer["points"].numpy().astype(np.float64)
        normals = self.normals[answer["primitive_ids"].numpy().astype(np.int64)]
        offset = points - closest
        dist = np.linalg.norm(offset, axis=1)
        sign = np.where(np.sum(offset * normals, axis=1) < 0, -1.0, 1.0)
        return sign * dist, closest, normals

    def first_hit(self, origins: FloatArray, directions: FloatArray) -> FloatArray:
        """Distance along each unit direction to the first hit (inf: none)."""
        rays = np.ascontiguousarray(np.hstack([origins, directions]), dtype=np.float32)
        answer = self.scene.cast_rays(self._o3d.core.Tensor.from_numpy(rays))
        return answer["t_hit"].numpy().astype(np.float64)


def signed_distances_m(points_m: FloatArray, mesh: TriangleMesh) -> FloatArray:
    """(N,) signed distance of each point to the mesh's surface, metres (positive outside)."""
    signed, _, _ = _Scene(mesh).closest(np.asarray(points_m, dtype=np.float64))
    return signed


def distance_figures(signed_m: FloatArray) -> dict[str, float]:
    """Signed mean, std, RMS, 95th percentile of |d| and max |d| of signed distances, metres."""
    absolute = np.abs(signed_m)
    return {"mean_m": float(signed_m.mean()), "std_m": float(signed_m.std()),
            "rms_m": float(np.sqrt(np.mean(signed_m**2))),
            "p95_m": float(np.percentile(absolute, 95)), "max_m": float(absolute.max())}


def visible_mask(points: FloatArray, normals: FloatArray, cameras: list[CameraInfo],
                 scene: _Scene, config: MetricsConfig) -> NDArray[np.bool_]:
    """(N,) whether some camera sees each surface sample (frustum, range, facing, unoccluded)."""
    seen = np.zeros(len(points), dtype=bool)
    for cam in cameras:
        if cam.world_from_depth is None:
            continue
        intr = cam.depth_intrinsics
        centre = cam.world_from_depth[:3, 3]
        pts_cam = transform(invert_rigid(cam.world_from_depth), points)
        to_point = points - centre
        dist = np.linalg.norm(to_point, axis=1)
        ray = to_point / np.maximum(dist[:, None], 1e-12)
        ok = ((pts_cam[:, 2] > 1e-6) & (dist >= config.min_range_m)
              & (dist <= config.max_range_m)
              & (-np.sum(ray * normals, axis=1) >= config.min_view_cos))
        pix = np.full((len(points), 2), -1.0)
        pix[ok] = project(intr, pts_cam[ok])
        ok &= ((pix[:, 0] >= -0.5) & (pix[:, 0] <= intr.width - 0.5)
               & (pix[:, 1] >= -0.5) & (pix[:, 1] <= intr.height - 0.5))
        idx = np.nonzero(ok & ~seen)[0]
        if len(idx) == 0:
            continue
        hit = scene.first_hit(np.repeat(centre[None], len(idx), axis=0), ray[idx])
        seen[idx[hit >= dist[idx] - config.occlusion_tolerance_m]] = True
    return seen


def compare(result: TriangleMesh, ground_truth: TriangleMesh, cameras: list[CameraInfo],
            config: MetricsConfig) -> dict[str, object]:
    """Accuracy (result -> GT), completeness (GT -> result), coverage and normal error, and
    the distances apart on the truth some camera observes and on the truth none observes
    (`visible_mask`; a result sample counts where its closest truth point lies).

    Returns a JSON-ready dict; distances in metres, angles in degrees, shares in [0, 1].
    """
    gt_scene, result_scene = _Scene(ground_truth), _Scene(result)
    res_pts, res_normals = sample_surface(result, config.sample_count, config.seed)
    signed, res_closest, gt_normals = gt_scene.closest(res_pts)
    cos = np.clip(np.sum(res_normals * gt_normals, axis=1), -1.0, 1.0)
    angle_deg = np.degrees(np.arccos(cos))
    gt_pts, gt_face_normals = sample_surface(ground_truth, config.sample_count, config.seed + 1)
    reverse, _, _ = result_scene.closest(gt_pts)
    visible = visible_mask(gt_pts, gt_face_normals, cameras, gt_scene, config)
    res_visible = visible_mask(res_closest, gt_normals, cameras, gt_scene, config)
    covered = np.abs(reverse) <= config.coverage_threshold_m
    return {
        "result_to_gt": distance_figures(signed),
        "gt_to_result": distance_figures(reverse),
        "visible_share": float(visible.mean()),
        "coverage_visible": float(covered[visible].mean()) if visible.any() else 0.0,
        "coverage_all": float(covered.mean()),
        "coverage_threshold_m": config.coverage_threshold_m,
        "normal_error_deg": {"mean": float(angle_deg.mean()),
                             "median": float(np.median(angle_deg)),
                             "p95": float(np.percentile(angle_deg, 95))},
        "observed": _part_figures(signed, angle_deg, res_visible, reverse, visible),
        "unobserved": _part_figures(signed, angle_deg, ~res_visible, reverse, ~visible),
        "samples": config.sample_count,
    }


def _part_figures(signed_m: FloatArray, angle_deg: FloatArray, result_in: NDArray[np.bool_],
                  reverse_m: FloatArray, truth_in: NDArray[np.bool_]) -> dict[str, float | None]:
    """RMS distances both ways and the mean normal error of the samples in one part of the
    truth, with the part's share of the truth's area (None: no sample lies there)."""
    def rms(values: FloatArray) -> float | None:
        return float(np.sqrt(np.mean(values**2))) if len(values) else None

    return {"truth_share": float(truth_in.mean()),
            "result_to_gt_rms_m": rms(signed_m[result_in]),
            "gt_to_result_rms_m": rms(reverse_m[truth_in]),
            "normal_error_mean_deg": float(angle_deg[result_in].mean()) if result_in.any()
            else None}


@dataclass(frozen=True)
class DepthAgreementConfig:
    """How a mesh is measured against the raw depth it was made from (no ground truth)."""

    bands_m: tuple[float, ...] = (0.0, 1.5, 2.5, 3.5, 4.5, 5.5)
    """Edges of the depth bands (along each camera's z), metres."""
    near_m: float = 0.05
    """A raw point is explained by the mesh when it lies within this distance, metres."""
    min_depth_m: float = 0.25
    """Raw depths nearer than this are outside the capture volume, metres."""
    max_depth_m: float = 5.5
    """Raw depths farther than this are outside the capture volume, metres."""
    pixel_step: int = 1
    """Every this many pixels (in x and y) of each depth image are measured."""

    def __post_init__(self) -> None:
        if len(self.bands_m) < 2 or np.any(np.diff(self.bands_m) <= 0):
            raise ValueError("depth agreement: bands_m must be at least two increasing edges")
        if self.pixel_step < 1 or not self.near_m > 0:
            raise ValueError("depth agreement: pixel_step >= 1 and near_m > 0 needed")


def raw_points(depth_m: NDArray[np.float32], camera: CameraInfo, config: DepthAgreementConfig
               ) -> tuple[FloatArray, FloatArray]:
    """(N, 3) world points of the raw depth within the range and (N,) their depths, metres."""
    from pipeline.reconstruct.registration import camera_points_image, ray_image

    if camera.world_from_depth is None:
        raise ValueError(f"camera {camera.id!r}: no world_from_depth")
    step = config.pixel_step
    depth = depth_m[::step, ::step]
    inside = (depth >= config.min_depth_m) & (depth <= config.max_depth_m)
    rays = ray_image(camera.depth_intrinsics)[::step, ::step]
    points_cam = camera_points_image(depth, rays)[inside].astype(np.float64)
    return transform(np.asarray(camera.world_from_depth), points_cam), depth[inside].astype(
        np.float64)


def depth_agreement(mesh: TriangleMesh, views: list[tuple[CameraInfo, NDArray[np.float32]]],
                    config: DepthAgreementConfig) -> dict[str, Any]:
    """How well the mesh explains each camera's raw depth (posed as the capture says).

    Per camera: the median distance of its raw points to the mesh. Per depth band (all
    cameras pooled): the share of raw points within ``near_m`` of the mesh. Millimetres and
    shares in [0, 1].
    """
    scene = _Scene(mesh)
    per_camera: dict[str, dict[str, float | int]] = {}
    depths, distances = [], []
    for camera, depth_m in views:
        points, depth = raw_points(depth_m, camera, config)
        if len(points) == 0:
            continue
        dist = np.abs(scene.closest(points)[0])
        per_camera[camera.id] = {"median_mm": round(float(np.median(dist)) * 1e3, 2),
                                 "within_near": round(float(np.mean(dist <= config.near_m)), 4),
                                 "points": len(points)}
        depths.append(depth)
        distances.append(dist)
    all_depth = np.concatenate(depths) if depths else np.zeros(0)
    all_dist = np.concatenate(distances) if distances else np.zeros(0)
    bands = {}
    for low, high in zip(config.bands_m[:-1], config.bands_m[1:], strict=True):
        in_band = (all_depth >= low) & (all_depth < high)
        share = float(np.mean(all_dist[in_band] <= config.near_m)) if in_band.any() else None
        bands[f"{low:g}-{high:g}"] = {"within_near": None if share is None else round(share, 4),
                                      "points": int(in_band.sum())}
    return {"cameras": per_camera, "bands_m": bands, "near_m": config.near_m}
