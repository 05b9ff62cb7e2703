"""Frame-sets of a stream as an agent sends them (docs/api.md, Streams): a zip of each camera's
16-bit depth PNG and optional colour, built in memory."""

from __future__ import annotations

import io
import zipfile
from collections.abc import Sequence
from typing import Any

import cv2
import numpy as np

WIDTH, HEIGHT = 64, 48
CAMERAS = ("cam0", "cam1")


def intrinsics(width: int = WIDTH, height: int = HEIGHT) -> dict[str, Any]:
    return {"width": width, "height": height, "fx": 60.0, "fy": 60.0, "cx": width / 2,
            "cy": height / 2}


def camera(camera_id: str, **extra: Any) -> dict[str, Any]:
    return {"id": camera_id, "depth_intrinsics": intrinsics(), **extra}


def stream_body(cameras: Sequence[str] = CAMERAS, **extra: Any) -> dict[str, Any]:
    return {"name": "test stream", "fps": 30.0, "depth_scale": 0.001,
            "cameras": [camera(c) for c in cameras], **extra}


def depth_png(index: int, width: int = WIDTH, height: int = HEIGHT, *,
              dtype: type = np.uint16) -> bytes:
    """A depth image whose values tell the frame apart (a plane at 1 m plus the index)."""
    value = 1000 + index if dtype is np.uint16 else 100
    depth = np.full((height, width), value, dtype=dtype)
    ok, data = cv2.imencode(".png", depth)
    assert ok
    return data.tobytes()


def color_jpeg(width: int = WIDTH, height: int = HEIGHT) -> bytes:
    ok, data = cv2.imencode(".jpg", np.full((height, width, 3), 128, np.uint8))
    assert ok
    return data.tobytes()


def frame_entries(index: int, cameras: Sequence[str] = CAMERAS, *,
                  color: bool = False) -> dict[str, bytes]:
    """Entry name -> bytes of a well-formed frame-set."""
    entries = {f"{c}/depth/{index:06d}.png": depth_png(index) for c in cameras}
    if color:
        entries.update({f"{c}/color/{index:06d}.jpg": color_jpeg() for c in cameras})
    return entries


def pack(entries: dict[str, bytes]) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_STORED) as archive:
        for name, data in entries.items():
            archive.writestr(name, data)
    return buffer.getvalue()


def frame_set(index: int, cameras: Sequence[str] = CAMERAS, *, color: bool = False) -> bytes:
    return pack(frame_entries(index, cameras, color=color))
