"""Streams for the live-preview tests: two posed cameras looking at a sphere, frame-set zips,
the agent's real preview.bin, and a gateway served by uvicorn in a thread."""

from __future__ import annotations

import contextlib
import io
import threading
import time
import zipfile
from collections.abc import Iterator
from typing import Any

import numpy as np

from agent.preview import encode_preview, pack_preview
from pipeline.capture import CameraInfo
from pipeline.io.png16 import encode_png16
from tests.integration.services import free_port
from tests.pipeline.sphere_scene import ring_cameras, sphere_depth

WIDTH, HEIGHT = 64, 48
DEPTH_SCALE = 0.001


def cameras() -> list[CameraInfo]:
    return ring_cameras(2, WIDTH, HEIGHT)


def camera_json(camera: CameraInfo) -> dict[str, Any]:
    """A camera as capture.json (and POST /streams) writes it."""
    intrinsics = camera.depth_intrinsics
    assert camera.world_from_depth is not None
    return {"id": camera.id,
            "depth_intrinsics": {"width": intrinsics.width, "height": intrinsics.height,
                                 "fx": intrinsics.fx, "fy": intrinsics.fy,
                                 "cx": intrinsics.cx, "cy": intrinsics.cy},
            "world_from_depth": camera.world_from_depth.tolist()}


def stream_body(name: str = "live test") -> dict[str, Any]:
    return {"name": name, "fps": 5.0, "depth_scale": DEPTH_SCALE,
            "cameras": [camera_json(camera) for camera in cameras()]}


DEPTH_M = {camera.id: sphere_depth(camera) for camera in cameras()}


def sphere_preview(index: int, captured_at: float | None = None) -> bytes:
    """The agent's preview of the sphere scene for frame ``index``."""
    return encode_preview(DEPTH_M, {}, cameras(), index,
                          time.time() if captured_at is None else captured_at)


def big_preview(index: int, points: int = 100_000) -> bytes:
    """A preview of ``points`` random points (large enough to fill socket buffers)."""
    rng = np.random.default_rng(index)
    return pack_preview(index, time.time(), rng.normal(size=(points, 3)).astype(np.float32),
                        rng.integers(0, 256, (points, 3), dtype=np.uint8))


def frame_set(index: int) -> bytes:
    """A frame-set zip: every camera's depth as a 16-bit PNG."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_STORED) as archive:
        for camera_id, depth_m in DEPTH_M.items():
            units = np.round(depth_m / DEPTH_SCALE).astype(np.uint16)
            archive.writestr(f"{camera_id}/depth/{index:06d}.png", encode_png16(units))
    return buffer.getvalue()


@contextlib.contextmanager
def served(app: Any) -> Iterator[str]:
    """``app`` served by uvicorn (its WebSocket support included) on a free port in a thread;
    yields the base URL."""
    import uvicorn

    port = free_port()
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port,
                                           log_level="warning"))
    thread = threading.Thread(target=server.run, name="uvicorn-live", daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not server.started:
        if not thread.is_alive() or time.monotonic() > deadline:
            raise RuntimeError("uvicorn did not start")
        time.sleep(0.02)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(15)
