"""One frame-set as the zip a stream takes (docs/api.md, "Streams"): every camera's depth as a
16-bit PNG and its colour as a JPEG (or PNG).

Depth is encoded with ISA-L (pipeline.io.png16), a camera a thread: its deflate releases the
GIL, so eight cameras share the cores. What is compressed already goes on as it is: a
recording's JPEG, a replayed capture's files (no decode and re-encode). Entries are stored,
not deflated: PNG and JPEG are compressed already (agent.stored_zip writes them in one pass).
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import Executor
from dataclasses import replace

import cv2
import numpy as np
from numpy.typing import NDArray

from agent.sources import CameraImages
from agent.stored_zip import stored_zip
from pipeline.capture import CameraInfo
from pipeline.io.capture_io import StoredFiles
from pipeline.io.png16 import encode_png16

JPEG_QUALITY = 90
_PREVIEW_JPEG_FLAG = cv2.IMREAD_REDUCED_COLOR_4
"""Preview colour is decoded at a quarter of each side (the JPEG decoder skips the rest):
a preview samples every few pixels anyway, and eight full 720p decodes cost ~40 ms."""


def depth_entry(camera_id: str, index: int) -> str:
    return f"{camera_id}/depth/{index:06d}.png"


def color_entry(camera_id: str, index: int, suffix: str = ".jpg") -> str:
    return f"{camera_id}/color/{index:06d}{suffix}"


def _stored_files(files: StoredFiles, index: int) -> list[tuple[str, bytes]]:
    entries = [(depth_entry(files.camera.id, index), files.depth_png)]
    if files.color is not None:
        suffix = ".png" if files.color_suffix == ".png" else ".jpg"  # .jpeg: a stream's .jpg
        entries.append((color_entry(files.camera.id, index, suffix), files.color))
    return entries


def _camera_files(images: CameraImages, index: int) -> list[tuple[str, bytes]]:
    if isinstance(images, StoredFiles):
        return _stored_files(images, index)
    entries = [(depth_entry(images.camera.id, index), encode_png16(images.depth_units))]
    if images.color_jpeg is not None:
        entries.append((color_entry(images.camera.id, index), images.color_jpeg))
    elif images.color_rgb is not None:
        bgr = np.ascontiguousarray(images.color_rgb[:, :, ::-1])
        ok, jpeg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        if not ok:
            raise ValueError(f"{images.camera.id}: could not encode frame {index}'s colour")
        entries.append((color_entry(images.camera.id, index), jpeg.tobytes()))
    return entries


def encode_frame_set(views: Sequence[CameraImages], index: int,
                     pool: Executor | None = None) -> bytes:
    """The zip of one frame-set numbered ``index``; cameras encoded side by side in ``pool``."""
    if pool is None:
        per_camera = [_camera_files(view, index) for view in views]
    else:
        per_camera = list(pool.map(lambda view: _camera_files(view, index), views))
    return stored_zip([entry for camera in per_camera for entry in camera])


def preview_inputs(views: Sequence[CameraImages], cameras: Sequence[CameraInfo],
                   depth_scale: float
                   ) -> tuple[dict[str, NDArray[np.float32]], dict[str, NDArray[np.uint8] | None],
                              list[CameraInfo]]:
    """What agent.preview.encode_preview takes: depth in metres, RGB colour, and ``cameras``
    (the views' cameras with their poses), colour intrinsics scaled to a colour image decoded
    at reduced size."""
    depth_m, colors, scaled = {}, {}, []
    for view, camera in zip(views, cameras, strict=True):
        units = _depth_units(view)
        depth_m[camera.id] = units.astype(np.float32) * np.float32(depth_scale)
        colors[camera.id], camera_as_decoded = _preview_color(view, camera)
        scaled.append(camera_as_decoded)
    return depth_m, colors, scaled


def _depth_units(view: CameraImages) -> NDArray[np.uint16]:
    if not isinstance(view, StoredFiles):
        return view.depth_units
    units = cv2.imdecode(np.frombuffer(view.depth_png, np.uint8), cv2.IMREAD_UNCHANGED)
    if units is None:
        raise ValueError(f"preview: camera {view.camera.id!r}: its depth PNG does not decode")
    return np.asarray(units, np.uint16)


def _preview_color(view: CameraImages, camera: CameraInfo
                   ) -> tuple[NDArray[np.uint8] | None, CameraInfo]:
    encoded = view.color if isinstance(view, StoredFiles) else view.color_jpeg
    if encoded is None:
        return (None if isinstance(view, StoredFiles) else view.color_rgb), camera
    reduced = camera.color_intrinsics is not None  # registered colour must keep depth's size
    bgr = cv2.imdecode(np.frombuffer(encoded, np.uint8),
                       _PREVIEW_JPEG_FLAG if reduced else cv2.IMREAD_COLOR)
    if bgr is None:
        return None, camera  # a broken image: the preview shows grey; the gateway judges it
    rgb: NDArray[np.uint8] = np.asarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), np.uint8)
    if not reduced:
        return rgb, camera
    assert camera.color_intrinsics is not None
    full = camera.color_intrinsics
    scale_x, scale_y = rgb.shape[1] / full.width, rgb.shape[0] / full.height
    # Pixel centres at integers: a pixel's edge (c + 0.5) scales, its centre does not.
    scaled = replace(full, width=rgb.shape[1], height=rgb.shape[0], fx=full.fx * scale_x,
                     fy=full.fy * scale_y, cx=(full.cx + 0.5) * scale_x - 0.5,
                     cy=(full.cy + 0.5) * scale_y - 0.5)
    return rgb, replace(camera, color_intrinsics=scaled)
