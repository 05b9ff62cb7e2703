"""The live preview an agent sends with a frame-set: ``preview.bin`` (``volumesh.preview/1``).

A downsampled point cloud of every camera's depth, fused in the world frame, with colour
(docs/api.md, "Live preview"). Layout, little-endian::

    uint32 H | H bytes UTF-8 JSON header | N*3 float32 positions (m) | N*3 uint8 RGB

Encoding runs on the rig PC at the capture rate, so it samples every k-th pixel of a fixed
grid (no filtering: a preview, not a measurement), with the grid's rays computed once per
camera, colour looked up without the colour lens's distortion, and numpy vectorised.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from pipeline.capture import CameraInfo, Intrinsics
from pipeline.reconstruct.registration import pixel_rays, project, transform

FORMAT = "volumesh.preview/1"
MAX_HEADER_BYTES = 4096
MAX_POINTS = 200_000
POINT_BYTES = 15
"""3 float32 position components and 3 uint8 colour channels."""
TARGET_POINTS = 60_000
"""The point budget of one preview (all cameras): the stride is chosen from the pixel count
so that a full frame-set stays under it (8 cameras of 640x576: every 8th pixel, <= 46 080)."""
GREY_NEAR_M, GREY_FAR_M = 0.5, 6.0
"""Depth range of the grey ramp used without colour (near light, far dark); fixed, so a
point keeps its shade from frame to frame."""

_LENGTH = struct.Struct("<I")


@dataclass(frozen=True)
class Preview:
    """A decoded ``preview.bin``."""

    frame_index: int
    captured_at: float
    """Agent wall clock (unix seconds) when the frame-set was captured."""
    positions_m: NDArray[np.float32]
    """(N, 3) world frame, metres (+Y up)."""
    colors: NDArray[np.uint8]
    """(N, 3) RGB."""


def stride_for(pixel_count: int, target_points: int = TARGET_POINTS) -> int:
    """The pixel step (in x and in y) that keeps ``pixel_count`` pixels under the budget."""
    return max(1, math.ceil(math.sqrt(pixel_count / target_points)))


def encode_preview(depth_m_by_camera: Mapping[str, NDArray[np.float32]],
                   color_by_camera: Mapping[str, NDArray[np.uint8] | None],
                   cameras: Sequence[CameraInfo], frame_index: int, captured_at: float
                   ) -> bytes:
    """``preview.bin`` of one frame-set: every camera's valid depth on a k-pixel grid.

    Raises ValueError when a camera has no ``world_from_depth`` (no preview without poses)
    or no depth image, or when a depth image is not the size of its intrinsics.
    """
    pixel_count = sum(cam.depth_intrinsics.width * cam.depth_intrinsics.height
                      for cam in cameras)
    stride = stride_for(pixel_count)
    positions, colors = [], []
    for cam in cameras:
        if cam.id not in depth_m_by_camera:
            raise ValueError(f"preview: no depth image for camera {cam.id!r}")
        cam_positions, cam_colors = camera_points(cam, depth_m_by_camera[cam.id],
                                                  color_by_camera.get(cam.id), stride)
        positions.append(cam_positions)
        colors.append(cam_colors)
    return pack_preview(frame_index, captured_at, np.concatenate(positions),
                        np.concatenate(colors))


def camera_points(cam: CameraInfo, depth_m: NDArray[np.float32],
                  color_rgb: NDArray[np.uint8] | None, stride: int
                  ) -> tuple[NDArray[np.float32], NDArray[np.uint8]]:
    """(N, 3) world positions and (N, 3) RGB of one camera's valid depth on the grid."""
    intrinsics = cam.depth_intrinsics
    if cam.world_from_depth is None:
        raise ValueError(f"preview: camera {cam.id!r} has no world_from_depth; a preview "
                         "needs every camera's pose")
    if depth_m.shape != (intrinsics.height, intrinsics.width):
        raise ValueError(f"preview: camera {cam.id!r} depth is {depth_m.shape[1]}x"
                         f"{depth_m.shape[0]}, its intrinsics say {intrinsics.width}x"
                         f"{intrinsics.height}")
    grid = _pixel_grid(intrinsics, stride)
    depth_grid_m = depth_m[grid.first::stride, grid.first::stride].ravel()
    valid = np.isfinite(depth_grid_m) & (depth_grid_m > 0)
    points_depth_m = grid.rays[valid] * depth_grid_m[valid, None]
    positions_m = transform(cam.world_from_depth, points_depth_m).astype(np.float32)
    grey = _grey_from_depth(depth_grid_m[valid])
    if color_rgb is None:
        return positions_m, grey
    if cam.color_intrinsics is None:  # registered: the colour pixel is the depth pixel
        return positions_m, _registered_colors(cam, color_rgb, grid.pixels_xy[valid])
    return positions_m, _projected_colors(cam, color_rgb, points_depth_m, grey)


@dataclass(frozen=True)
class _Grid:
    first: int
    """The first sampled row and column (then every ``stride``-th)."""
    pixels_xy: NDArray[np.intp]
    """(N, 2) integer pixel (x, y) of each grid point, row-major like ``rays``."""
    rays: NDArray[np.float64]
    """(N, 3) rays (x/z, y/z, 1) through the grid's pixel centres."""


@functools.lru_cache(maxsize=64)
def _pixel_grid(intrinsics: Intrinsics, stride: int) -> _Grid:
    # Cached: a rig's cameras keep their intrinsics, so the rays are computed once per run,
    # which makes the depth lens's distortion model free to honour (the colour projection,
    # done every frame, leaves it out). The grid starts half a step in, centring the samples.
    first = stride // 2
    xs, ys = np.meshgrid(np.arange(first, intrinsics.width, stride),
                         np.arange(first, intrinsics.height, stride))
    pixels_xy = np.column_stack([xs.ravel(), ys.ravel()])
    rays = pixel_rays(intrinsics, pixels_xy.astype(np.float64))
    pixels_xy.flags.writeable = False
    rays.flags.writeable = False
    return _Grid(first, pixels_xy, rays)


def _undistorted(intrinsics: Intrinsics) -> Intrinsics:
    # The colour lookup ignores lens distortion: projecting through the model costs ~2.5 ms
    # a camera (cv2.projectPoints), more than the rest of the encoding, and a colour a few
    # pixels off near the image corners does not show in a preview.
    return dataclasses.replace(intrinsics, distortion=())


def _grey_from_depth(depth_m: NDArray[np.float32]) -> NDArray[np.uint8]:
    near = np.clip((GREY_FAR_M - depth_m) / (GREY_FAR_M - GREY_NEAR_M), 0.0, 1.0)
    level = (60 + 180 * near).astype(np.uint8)
    return np.repeat(level[:, None], 3, axis=1)


def _registered_colors(cam: CameraInfo, color_rgb: NDArray[np.uint8],
                       pixels_xy: NDArray[np.intp]) -> NDArray[np.uint8]:
    size = (cam.depth_intrinsics.height, cam.depth_intrinsics.width)
    if color_rgb.shape[:2] != size:
        raise ValueError(f"preview: camera {cam.id!r} has registered colour of "
                         f"{color_rgb.shape[1]}x{color_rgb.shape[0]}, its depth is "
                         f"{size[1]}x{size[0]}")
    return np.ascontiguousarray(color_rgb[pixels_xy[:, 1], pixels_xy[:, 0], :3])


def _projected_colors(cam: CameraInfo, color_rgb: NDArray[np.uint8],
                      points_depth_m: NDArray[np.float64], grey: NDArray[np.uint8]
                      ) -> NDArray[np.uint8]:
    """Colour at each point's projection in the colour image; grey where it falls outside."""
    assert cam.color_intrinsics is not None
    color_from_depth = cam.color_from_depth if cam.color_from_depth is not None else np.eye(4)
    points_color_m = transform(color_from_depth, points_depth_m)
    in_front = points_color_m[:, 2] > 1e-6
    colors = grey.copy()
    if not in_front.any():
        return colors
    pixels = project(_undistorted(cam.color_intrinsics), points_color_m[in_front])
    columns = np.floor(pixels[:, 0] + 0.5).astype(np.intp)  # nearest pixel centre
    rows = np.floor(pixels[:, 1] + 0.5).astype(np.intp)
    height, width = color_rgb.shape[:2]
    inside = (columns >= 0) & (columns < width) & (rows >= 0) & (rows < height)
    target = np.flatnonzero(in_front)[inside]
    colors[target] = color_rgb[rows[inside], columns[inside], :3]
    return colors


def pack_preview(frame_index: int, captured_at: float, positions_m: NDArray[np.float32],
                 colors: NDArray[np.uint8]) -> bytes:
    """The ``preview.bin`` bytes of a point cloud (at most ``MAX_POINTS`` points)."""
    count = len(positions_m)
    if count > MAX_POINTS:
        raise ValueError(f"preview: {count} points, at most {MAX_POINTS}")
    if positions_m.shape != (count, 3) or colors.shape != (count, 3):
        raise ValueError("preview: positions and colours must both be (N, 3)")
    header = json.dumps({"format": FORMAT, "frame_index": int(frame_index),
                         "captured_at": float(captured_at), "points": count},
                        separators=(",", ":")).encode()
    # Trailing spaces (still valid JSON) put the positions on a 4-byte boundary, so a browser
    # can view them as a Float32Array without a copy.
    header += b" " * (-(_LENGTH.size + len(header)) % 4)
    return b"".join([_LENGTH.pack(len(header)), header,
                     np.ascontiguousarray(positions_m, dtype="<f4").tobytes(),
                     np.ascontiguousarray(colors, dtype=np.uint8).tobytes()])


def decode_preview(data: bytes) -> Preview:
    """The preview in ``data``; ValueError saying what is wrong with a malformed buffer."""
    header, body_at = _read_header(data)
    count = header["points"]
    expected = body_at + POINT_BYTES * count
    if len(data) != expected:
        raise ValueError(f"preview: {len(data)} bytes, but a header of {body_at - 4} bytes "
                         f"and {count} points need exactly {expected}")
    positions_m = np.frombuffer(data, dtype="<f4", count=3 * count, offset=body_at)
    if not np.isfinite(positions_m).all():
        raise ValueError("preview: positions hold NaN or infinite values")
    colors = np.frombuffer(data, dtype=np.uint8, count=3 * count, offset=body_at + 12 * count)
    return Preview(frame_index=header["frame_index"], captured_at=float(header["captured_at"]),
                   positions_m=positions_m.astype(np.float32).reshape(count, 3),
                   colors=colors.reshape(count, 3).copy())


def _read_header(data: bytes) -> tuple[dict, int]:
    if len(data) < _LENGTH.size:
        raise ValueError(f"preview: {len(data)} bytes, too short for its header length")
    (length,) = _LENGTH.unpack_from(data, 0)
    if length > MAX_HEADER_BYTES:
        raise ValueError(f"preview: header length {length}, at most {MAX_HEADER_BYTES}")
    body_at = _LENGTH.size + length
    if len(data) < body_at:
        raise ValueError(f"preview: {len(data)} bytes, shorter than its {length}-byte header")
    try:
        header = json.loads(data[_LENGTH.size:body_at].decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"preview: the header is not UTF-8 JSON ({exc})") from None
    _check_header(header)
    return header, body_at


def _check_header(header: object) -> None:
    if not isinstance(header, dict):
        raise ValueError("preview: the header is not a JSON object")
    if header.get("format") != FORMAT:
        raise ValueError(f"preview: format {header.get('format')!r}, expected {FORMAT!r}")
    for name in ("frame_index", "points"):
        value = header.get(name)
        if not isinstance(value, int) or isinstance(value, bool) or value < 0:
            raise ValueError(f"preview: header {name} must be an integer >= 0, got {value!r}")
    captured_at = header.get("captured_at")
    if (not isinstance(captured_at, int | float) or isinstance(captured_at, bool)
            or not math.isfinite(captured_at)):
        raise ValueError(f"preview: header captured_at must be a finite number, "
                         f"got {captured_at!r}")
    if header["points"] > MAX_POINTS:
        raise ValueError(f"preview: {header['points']} points, at most {MAX_POINTS}")
