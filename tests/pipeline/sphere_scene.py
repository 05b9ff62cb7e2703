"""Analytic depth maps of a sphere seen by a ring of pinhole cameras (test scenes)."""

from __future__ import annotations

import math

import numpy as np
import trimesh

from pipeline.capture import CameraInfo, CaptureMeta, FrameInfo, Intrinsics, View
from pipeline.geometry.mesh import TriangleMesh

CENTRE = np.array([0.0, 1.0, 0.0])
RADIUS = 0.3


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """4x4 world_from_camera of an OpenCV camera at eye looking at target, +Y up."""
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = x, y, z, eye
    return pose


def ring_cameras(count: int, width: int, height: int, distance: float = 1.2,
                 distortion: tuple[float, ...] = ()) -> list[CameraInfo]:
    """Cameras on a ring around the sphere, alternately above and below its centre."""
    f = (width / 2) / math.tan(math.radians(37.5))
    intr = Intrinsics(width=width, height=height, fx=f, fy=f, cx=(width - 1) / 2,
                      cy=(height - 1) / 2, distortion=distortion)
    cams = []
    for i in range(count):
        azimuth = 2 * math.pi * i / count
        lift = 0.5 if i % 2 == 0 else -0.3
        eye = CENTRE + distance * np.array([math.sin(azimuth), lift, math.cos(azimuth)])
        cams.append(CameraInfo(id=f"cam{i}", depth_intrinsics=intr,
                               world_from_depth=look_at(eye, CENTRE)))
    return cams


def sphere_depth(camera: CameraInfo, bias_m: float = 0.0, noise_m: float = 0.0,
                 rng: np.random.Generator | None = None,
                 spheres: tuple[tuple[np.ndarray, float], ...] = ((CENTRE, RADIUS),),
                 pose: np.ndarray | None = None) -> np.ndarray:
    """(H, W) float32 z-depth of the spheres (0 where rays miss); range += bias + noise.

    Rendered from ``pose`` (default: the camera's own world_from_depth).
    """
    from pipeline.reconstruct.registration import ray_image

    pose = camera.world_from_depth if pose is None else pose
    assert pose is not None
    rays = ray_image(camera.depth_intrinsics).astype(np.float64)
    unit = rays / np.linalg.norm(rays, axis=2, keepdims=True)
    world = unit @ pose[:3, :3].T
    t = np.full(rays.shape[:2], np.inf)
    for centre, radius in spheres:
        origin = pose[:3, 3] - centre
        b = world @ origin
        disc = b * b - (origin @ origin - radius**2)
        hit = np.where(disc > 0, -b - np.sqrt(np.maximum(disc, 0.0)), np.inf)
        t = np.minimum(t, np.where(hit > 0, hit, np.inf))
    hit = np.isfinite(t)
    t = np.where(hit, t, 0.0)
    if noise_m > 0:
        assert rng is not None
        t = t + rng.normal(0.0, noise_m, t.shape)
    depth = (t + bias_m) * unit[..., 2]
    return np.where(hit, depth, 0.0).astype(np.float32)


def sphere_views(cameras: list[CameraInfo], biases_m: list[float] | None = None,
                 noise_m: float = 0.0, seed: int = 0) -> list[View]:
    rng = np.random.default_rng(seed)
    biases = biases_m or [0.0] * len(cameras)
    return [View(camera=cam, frame_index=0,
                 depth_m=sphere_depth(cam, bias, noise_m, rng),
                 color_rgb=np.full((cam.depth_intrinsics.height, cam.depth_intrinsics.width, 3),
                                   200, dtype=np.uint8))
            for cam, bias in zip(cameras, biases, strict=True)]


def sphere_meta(cameras: list[CameraInfo], depth_scale: float = 0.0001) -> CaptureMeta:
    return CaptureMeta(depth_scale=depth_scale, cameras=tuple(cameras),
                       frames=(FrameInfo(index=0, timestamp_us=0),))


def sphere_mesh(subdivisions: int = 5) -> TriangleMesh:
    """The ground-truth sphere as a fine icosphere."""
    ico = trimesh.creation.icosphere(subdivisions=subdivisions, radius=RADIUS)
    return TriangleMesh(vertices_m=np.asarray(ico.vertices) + CENTRE,
                        faces=np.asarray(ico.faces, dtype=np.int32))


def sphere_cloud(count: int, noise_m: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(count, 3) points on the sphere, moved along its normal by Gaussian noise of noise_m,
    and their (count, 3) float32 unit normals."""
    rng = np.random.default_rng(seed)
    normals = rng.normal(size=(count, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    points = CENTRE + normals * (RADIUS + rng.normal(0, noise_m, size=(count, 1)))
    return points, normals.astype(np.float32)


def distance_to_sphere(points: np.ndarray) -> np.ndarray:
    """Signed distance of (N, 3) points to the analytic sphere (positive outside)."""
    return np.linalg.norm(points - CENTRE, axis=1) - RADIUS
