"""In-memory model of a capture in format v1 (docs/capture-format.md).

These are plain frozen dataclasses; reading and writing them lives in
:mod:`pipeline.io.capture_io`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

FORMAT_ID = "volumesh.capture/1"
CAMERA_ID_PATTERN = r"[A-Za-z0-9_-]{1,32}"


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole camera model in pixels; distortion in OpenCV order (any prefix of 8)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...] = ()

    def matrix(self) -> NDArray[np.float64]:
        """The 3x3 camera matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def distortion_coeffs(self) -> NDArray[np.float64]:
        """Distortion coefficients padded to OpenCV's 8 (zeros where absent)."""
        coeffs = np.zeros(8)
        coeffs[: len(self.distortion)] = self.distortion
        return coeffs

    @property
    def has_distortion(self) -> bool:
        return any(c != 0.0 for c in self.distortion)


@dataclass(frozen=True)
class CameraInfo:
    """One camera of the rig: its models and where it stands."""

    id: str
    depth_intrinsics: Intrinsics
    color_intrinsics: Intrinsics | None = None
    """None: colour is registered to the depth pixels (same size and model)."""
    color_from_depth: NDArray[np.float64] | None = None
    """4x4 rigid transform, metres; None with registered colour."""
    world_from_depth: NDArray[np.float64] | None = None
    """4x4 rigid camera pose in the world (+Y up), metres; None when unknown."""


@dataclass(frozen=True)
class FrameInfo:
    index: int
    timestamp_us: int


@dataclass(frozen=True)
class BoardSpec:
    """One ChArUco board of a calibration target (frame as OpenCV's getChessboardCorners)."""

    dictionary: str
    squares_x: int
    squares_y: int
    square_length_m: float
    marker_length_m: float
    first_marker_id: int
    target_from_board: NDArray[np.float64] = field(default_factory=lambda: np.eye(4))


@dataclass(frozen=True)
class Target:
    boards: tuple[BoardSpec, ...]


@dataclass(frozen=True)
class CaptureMeta:
    """Everything capture.json says."""

    depth_scale: float
    """Metres per depth unit."""
    cameras: tuple[CameraInfo, ...]
    frames: tuple[FrameInfo, ...]
    target: Target | None = None

    def camera(self, camera_id: str) -> CameraInfo:
        for cam in self.cameras:
            if cam.id == camera_id:
                return cam
        raise ValueError(f"capture has no camera {camera_id!r}")

    @property
    def camera_ids(self) -> tuple[str, ...]:
        return tuple(cam.id for cam in self.cameras)

    @property
    def frame_indices(self) -> tuple[int, ...]:
        return tuple(f.index for f in self.frames)


@dataclass(frozen=True)
class View:
    """One camera's images at one frame, decoded."""

    camera: CameraInfo
    frame_index: int
    depth_m: NDArray[np.float32]
    """(H, W) metres along the camera's z axis; 0 where there is no measurement."""
    color_rgb: NDArray[np.uint8] | None = None
    """(Hc, Wc, 3) RGB, registered to depth when camera.color_intrinsics is None."""
