"""Noise-free synthetic ChArUco observations for the geometry tests (no images)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from pipeline.calibration.detection import TargetGeometry, ViewCorners, target_geometry
from pipeline.calibration.transforms import invert, rigid
from pipeline.capture import BoardSpec, Target

Matrix = NDArray[np.float64]
CAMERA_MATRIX = np.array([[600.0, 0.0, 640.0], [0.0, 600.0, 360.0], [0.0, 0.0, 1.0]])


def plane_geometry() -> TargetGeometry:
    return target_geometry(Target(boards=(BoardSpec("DICT_5X5_100", 6, 5, 0.08, 0.06, 0),)))


def look_at(eye: Matrix, target: Matrix) -> Matrix:
    """world_from_camera of an OpenCV camera at eye looking at target, x axis horizontal."""
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    return rigid(np.column_stack([x, np.cross(z, x), z]), eye)


def ring_cameras(count: int, rng: np.random.Generator, spread_deg: float = 100.0
                 ) -> list[Matrix]:
    """world_from_camera of cameras ~2 m from the origin, all in front of the board's face."""
    poses = []
    for i in range(count):
        azimuth = np.radians(-spread_deg / 2 + spread_deg * i / max(count - 1, 1))
        azimuth += rng.uniform(-0.05, 0.05)
        height = rng.uniform(-0.6, 0.6)
        eye = np.array([2.0 * np.sin(azimuth), height, -2.0 * np.cos(azimuth)])
        poses.append(look_at(eye, rng.uniform(-0.1, 0.1, 3)))
    return poses


def target_poses(count: int, rng: np.random.Generator) -> list[Matrix]:
    """world_from_target near the origin, the printed face towards -z (the cameras)."""
    poses = []
    for _ in range(count):
        tilt = rng.uniform(-0.35, 0.35, 3)
        rotation = _rotvec(tilt)
        centre = np.array([0.2, 0.16, 0.0])
        poses.append(rigid(rotation, rng.uniform(-0.2, 0.2, 3) - rotation @ centre))
    return poses


def _rotvec(v: Matrix) -> Matrix:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(v).as_matrix()


def observe(geometry: TargetGeometry, world_from_camera: list[Matrix],
            world_from_target: list[Matrix], camera_ids: list[str]) -> list[ViewCorners]:
    """Exact pixels of every corner in every camera (all lie in front of the cameras)."""
    views = []
    for cam_id, cam_pose in zip(camera_ids, world_from_camera, strict=True):
        for frame, target_pose in enumerate(world_from_target):
            camera_from_target = invert(cam_pose) @ target_pose
            points = geometry.points_target @ camera_from_target[:3, :3].T \
                + camera_from_target[:3, 3]
            assert np.all(points[:, 2] > 0)
            pixels = points @ CAMERA_MATRIX.T
            views.append(ViewCorners(cam_id, frame, np.arange(len(points)),
                                     pixels[:, :2] / pixels[:, 2:3]))
    return views
