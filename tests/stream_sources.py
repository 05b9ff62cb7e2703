"""Captures for the agent to replay: many frames of small images, each frame's depth telling
it apart, with poses (so the agent sends previews) and timestamps at a given rate."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.capture import CameraInfo, CaptureMeta, FrameInfo, Intrinsics
from pipeline.io.capture_io import StoredView, write_capture


def _camera(camera_id: str, x_m: float) -> CameraInfo:
    pose = np.eye(4)
    pose[:3, 3] = (x_m, 1.0, 2.0)
    pose[:3, :3] = np.diag([1.0, -1.0, -1.0])  # looking down -Z of a +Y-up world
    return CameraInfo(id=camera_id, depth_intrinsics=Intrinsics(64, 48, 60.0, 60.0, 32.0, 24.0),
                      world_from_depth=pose)


def replay_capture(folder: Path, frames: int, fps: float, cameras: int = 2) -> Path:
    """A capture directory of ``frames`` frames of ``cameras`` 64x48 cameras at ``fps``; frame
    i's depth is a plane at 1000 + i mm (cached per parameters)."""
    out = folder / f"replay-{cameras}x{frames}@{fps:g}"
    if (out / "capture.json").is_file():
        return out
    rig = tuple(_camera(f"cam{i}", 0.3 * i) for i in range(cameras))
    meta = CaptureMeta(depth_scale=0.001, cameras=rig,
                       frames=tuple(FrameInfo(i, round(i * 1e6 / fps)) for i in range(frames)))
    views = (StoredView(camera=camera, frame_index=i,
                        depth_units=np.full((48, 64), 1000 + i, np.uint16))
             for i in range(frames) for camera in rig)
    write_capture(out, meta, views)
    return out
