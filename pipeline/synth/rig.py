"""The camera rig of the synthetic captures: two rings of depth cameras facing the subject.

World frame: metres, +Y up, the floor is y = 0 and the subject stands around the origin.
Camera frames are OpenCV's (x right, y down, z forward).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from pipeline.capture import CameraInfo, Intrinsics


@dataclass(frozen=True)
class RigConfig:
    """Where the cameras stand and what they see (defaults: an Azure Kinect NFOV rig)."""

    camera_count: int = 8
    """Cameras in all; the upper ring gets ceil(n/2) of them, the lower ring the rest."""
    upper_height_m: float = 2.0
    """Height of the upper ring's cameras above the floor, metres."""
    lower_height_m: float = 1.0
    """Height of the lower ring's cameras above the floor, metres."""
    radius_m: float = 2.0
    """Horizontal distance of every camera from the subject's vertical axis, metres."""
    target_m: tuple[float, float, float] = (0.0, 0.9, 0.0)
    """World point every camera looks at (the subject's centre), metres."""
    width: int = 640
    """Depth image width, pixels (Azure Kinect NFOV unbinned: 640)."""
    height: int = 576
    """Depth image height, pixels (Azure Kinect NFOV unbinned: 576)."""
    fov_x_deg: float = 75.0
    """Horizontal field of view, degrees (Azure Kinect NFOV: 75)."""
    fov_y_deg: float = 65.0
    """Vertical field of view, degrees (Azure Kinect NFOV: 65)."""
    azimuth_offset_deg: float = 0.0
    """Azimuth of the first upper camera, degrees about +Y from +Z towards +X."""

    def __post_init__(self) -> None:
        if self.camera_count < 1:
            raise ValueError(f"camera_count: must be at least 1, got {self.camera_count}")
        if self.radius_m <= 0:
            raise ValueError(f"radius_m: must be positive, got {self.radius_m}")
        if self.width < 2 or self.height < 2:
            raise ValueError(f"width/height: image too small ({self.width}x{self.height})")
        for name in ("fov_x_deg", "fov_y_deg"):
            if not 1.0 <= getattr(self, name) < 179.0:
                raise ValueError(f"{name}: must lie in [1, 179) degrees")


def rig_intrinsics(config: RigConfig) -> Intrinsics:
    """The pinhole model with the configured image size and fields of view, no distortion.

    The Azure Kinect's NFOV mode is specified as 75 x 65 degrees; a pinhole model with those
    angles has slightly non-square pixels, which every consumer of `Intrinsics` handles.
    """
    fx = (config.width / 2) / math.tan(math.radians(config.fov_x_deg) / 2)
    fy = (config.height / 2) / math.tan(math.radians(config.fov_y_deg) / 2)
    # OpenCV puts pixel centres at integer coordinates, so the image centre is (W-1)/2.
    return Intrinsics(width=config.width, height=config.height, fx=fx, fy=fy,
                      cx=(config.width - 1) / 2, cy=(config.height - 1) / 2)


def look_at(eye_m: NDArray[np.float64], target_m: NDArray[np.float64]) -> NDArray[np.float64]:
    """4x4 world_from_camera of an OpenCV camera at `eye_m` looking at `target_m` (+Y up).

    The camera's x axis stays horizontal; raises ValueError when looking straight up or down.
    """
    eye = np.asarray(eye_m, dtype=np.float64)
    forward = np.asarray(target_m, dtype=np.float64) - eye
    norm = np.linalg.norm(forward)
    if norm == 0:
        raise ValueError("look_at: eye and target coincide")
    z_axis = forward / norm
    right = np.cross(z_axis, [0.0, 1.0, 0.0])
    if np.linalg.norm(right) < 1e-9:
        raise ValueError("look_at: viewing direction is vertical, the image x axis is undefined")
    x_axis = right / np.linalg.norm(right)
    y_axis = np.cross(z_axis, x_axis)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = x_axis, y_axis, z_axis, eye
    return pose


def ring_layout(config: RigConfig) -> list[tuple[float, float]]:
    """(azimuth degrees, height metres) of each camera: upper ring first, then lower.

    The lower ring is turned by half the spacing of its cameras (45 degrees with 4 + 4), so
    the two rings see the subject from interleaved directions.
    """
    upper = (config.camera_count + 1) // 2
    lower = config.camera_count - upper
    layout = [(config.azimuth_offset_deg + 360.0 * i / upper, config.upper_height_m)
              for i in range(upper)]
    layout += [(config.azimuth_offset_deg + 360.0 * (i + 0.5) / lower, config.lower_height_m)
               for i in range(lower)]
    return layout


def rig_cameras(config: RigConfig) -> list[CameraInfo]:
    """One `CameraInfo` per camera, ids cam0.., with the true `world_from_depth`."""
    intrinsics = rig_intrinsics(config)
    target = np.asarray(config.target_m, dtype=np.float64)
    cameras = []
    for index, (azimuth_deg, height_m) in enumerate(ring_layout(config)):
        azimuth = math.radians(azimuth_deg)
        eye = np.array([target[0] + config.radius_m * math.sin(azimuth), height_m,
                        target[2] + config.radius_m * math.cos(azimuth)])
        cameras.append(CameraInfo(id=f"cam{index}", depth_intrinsics=intrinsics,
                                  world_from_depth=look_at(eye, target)))
    return cameras
