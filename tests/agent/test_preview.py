"""The agent's live preview (``preview.bin``): geometry, colour, size, speed and malformed input."""

from __future__ import annotations

import json
import math
import struct
import time

import numpy as np
import pytest

from agent.preview import (
    MAX_POINTS,
    TARGET_POINTS,
    decode_preview,
    encode_preview,
    pack_preview,
)
from pipeline.capture import CameraInfo, Intrinsics
from tests.pipeline.sphere_scene import CENTRE, RADIUS, ring_cameras, sphere_depth

WIDTH, HEIGHT = 160, 120


def _rotation_y(angle_rad: float) -> np.ndarray:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _two_cameras() -> list[CameraInfo]:
    """Two cameras on opposite sides of the sphere, the second with a colour camera offset by
    3 cm and turned 2 degrees, of its own size and focal length."""
    first, second = ring_cameras(2, WIDTH, HEIGHT)
    color_from_depth = np.eye(4)
    color_from_depth[:3, :3] = _rotation_y(math.radians(2))
    color_from_depth[:3, 3] = [-0.03, 0.002, 0.0]
    color = Intrinsics(width=200, height=150, fx=150.0, fy=150.0, cx=99.5, cy=74.5)
    second = CameraInfo(second.id, second.depth_intrinsics, color, color_from_depth,
                        second.world_from_depth)
    return [first, second]


def _coordinate_image(width: int, height: int) -> np.ndarray:
    """An RGB image whose red is the pixel's column and green its row (both < 256)."""
    image = np.full((height, width, 3), 200, np.uint8)
    image[..., 0] = np.arange(width)[None, :]
    image[..., 1] = np.arange(height)[:, None]
    return image


def _project(intrinsics: Intrinsics, camera_from_world: np.ndarray, points_m: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    cam = points_m.astype(np.float64) @ camera_from_world[:3, :3].T + camera_from_world[:3, 3]
    pixels = np.column_stack([intrinsics.fx * cam[:, 0] / cam[:, 2] + intrinsics.cx,
                              intrinsics.fy * cam[:, 1] / cam[:, 2] + intrinsics.cy])
    return pixels, cam[:, 2]


def _scene() -> tuple[list[CameraInfo], dict[str, np.ndarray], dict[str, np.ndarray | None]]:
    cameras = _two_cameras()
    depth = {cam.id: sphere_depth(cam) for cam in cameras}
    colors: dict[str, np.ndarray | None] = {
        cameras[0].id: _coordinate_image(WIDTH, HEIGHT),  # registered
        cameras[1].id: _coordinate_image(200, 150)}
    return cameras, depth, colors


def test_round_trip() -> None:
    rng = np.random.default_rng(1)
    positions = rng.normal(size=(1234, 3)).astype(np.float32)
    colors = rng.integers(0, 256, (1234, 3), dtype=np.uint8)
    data = pack_preview(42, 1_700_000_000.25, positions, colors)
    (header_bytes,) = struct.unpack_from("<I", data)
    assert (4 + header_bytes) % 4 == 0  # positions 4-byte aligned for a Float32Array view
    assert len(data) == 4 + header_bytes + 15 * 1234
    preview = decode_preview(data)
    assert preview.frame_index == 42
    assert preview.captured_at == 1_700_000_000.25
    np.testing.assert_array_equal(preview.positions_m, positions)
    np.testing.assert_array_equal(preview.colors, colors)
    assert decode_preview(pack_preview(0, 0.0, positions[:0], colors[:0])).positions_m.shape \
        == (0, 3)


def test_points_lie_where_the_geometry_says() -> None:
    cameras, depth, _ = _scene()
    preview = decode_preview(encode_preview(depth, {}, cameras, 7, 12.5))
    assert (preview.frame_index, preview.captured_at) == (7, 12.5)
    valid = [int((depth[cam.id] > 0).sum()) for cam in cameras]
    # Two 160x120 cameras are under the budget: every pixel with depth is a point.
    assert len(preview.positions_m) == sum(valid)
    offsets = preview.positions_m - CENTRE
    distance_m = np.linalg.norm(offsets, axis=1)
    footprint_m = 1.2 / cameras[0].depth_intrinsics.fx  # a pixel's size at the sphere
    assert np.abs(distance_m - RADIUS).max() < footprint_m
    # Each camera's points are on the side of the sphere that faces it (its pose is used).
    for cam, points in zip(cameras, np.split(offsets, [valid[0]]), strict=True):
        assert cam.world_from_depth is not None
        towards_camera = cam.world_from_depth[:3, 3] - CENTRE
        assert (points @ towards_camera > 0).all()


def test_the_depth_lens_distortion_is_honoured() -> None:
    cameras = ring_cameras(2, WIDTH, HEIGHT, distortion=(-0.3, 0.1, 0.002, -0.001))
    depth = {cam.id: sphere_depth(cam) for cam in cameras}  # rendered through the lens model
    preview = decode_preview(encode_preview(depth, {}, cameras, 0, 0.0))
    distance_m = np.linalg.norm(preview.positions_m - CENTRE, axis=1)
    assert np.abs(distance_m - RADIUS).max() < 1e-4


def test_colour_sampled_at_the_projected_pixel() -> None:
    cameras, depth, colors = _scene()
    preview = decode_preview(encode_preview(depth, colors, cameras, 0, 0.0))
    first_count = int((depth[cameras[0].id] > 0).sum())
    positions = np.split(preview.positions_m, [first_count])
    sampled = np.split(preview.colors.astype(np.float64), [first_count])

    # Registered colour: the depth pixel itself.
    first = cameras[0]
    assert first.world_from_depth is not None
    pixels, _ = _project(first.depth_intrinsics, np.linalg.inv(first.world_from_depth),
                         positions[0])
    assert np.abs(sampled[0][:, :2] - pixels).max() < 1e-3

    # A colour camera of its own: the nearest pixel to the point's projection in it, grey
    # where the point falls outside the colour image.
    second = cameras[1]
    assert second.world_from_depth is not None and second.color_from_depth is not None
    assert second.color_intrinsics is not None
    color_from_world = second.color_from_depth @ np.linalg.inv(second.world_from_depth)
    pixels, _ = _project(second.color_intrinsics, color_from_world, positions[1])
    inside = ((pixels > -0.5) & (pixels < [199.5, 149.5])).all(axis=1)
    assert inside.mean() > 0.5
    assert np.abs(sampled[1][inside, :2] - pixels[inside]).max() <= 0.5 + 1e-3
    assert (sampled[1][inside, 2] == 200).all()
    outside = sampled[1][~inside]
    assert (outside == outside[:, :1]).all()  # grey


def test_grey_from_depth_without_colour() -> None:
    camera = ring_cameras(1, WIDTH, HEIGHT)[0]
    depth_m = np.full((HEIGHT, WIDTH), 1.0, np.float32)
    depth_m[:, WIDTH // 2:] = 4.0
    preview = decode_preview(encode_preview({camera.id: depth_m}, {camera.id: None}, [camera],
                                            0, 0.0))
    grey = preview.colors.astype(int)
    assert (grey == grey[:, :1]).all()
    assert camera.world_from_depth is not None
    ranges_m = np.linalg.norm(preview.positions_m - camera.world_from_depth[:3, 3], axis=1)
    near, far = grey[ranges_m < 2, 0], grey[ranges_m > 2, 0]
    assert len(near) == len(far) == WIDTH * HEIGHT // 2
    assert near.min() > far.max() + 50  # nearer is lighter


def test_eight_full_cameras_stay_under_the_budget_and_fast() -> None:
    intrinsics = Intrinsics(width=640, height=576, fx=504.0, fy=504.0, cx=319.5, cy=287.5,
                            distortion=(0.5, -0.1, 0.0, 0.0, 0.01))
    color = Intrinsics(width=1280, height=720, fx=600.0, fy=600.0, cx=639.5, cy=359.5)
    rng = np.random.default_rng(0)
    cameras, depth, colors = [], {}, {}
    for k in range(8):
        pose = np.eye(4)
        pose[:3, :3] = _rotation_y(2 * math.pi * k / 8)
        cameras.append(CameraInfo(f"cam{k}", intrinsics, color, np.eye(4), pose))
        depth[f"cam{k}"] = rng.uniform(0.5, 5.0, (576, 640)).astype(np.float32)
        colors[f"cam{k}"] = rng.integers(0, 256, (720, 1280, 3), dtype=np.uint8)
    data = encode_preview(depth, colors, cameras, 3, time.time())
    count = len(decode_preview(data).positions_m)
    assert 0.6 * TARGET_POINTS < count <= TARGET_POINTS
    assert len(data) < 4096 + 15 * TARGET_POINTS
    timings_s = []
    for _ in range(5):
        started = time.perf_counter()
        encode_preview(depth, colors, cameras, 3, time.time())
        timings_s.append(time.perf_counter() - started)
    # 5 Hz leaves 200 ms a frame-set; the encoder takes a few ms a camera.
    assert sorted(timings_s)[2] < 0.1


def test_cameras_without_a_pose_or_depth_are_refused() -> None:
    cameras, depth, _ = _scene()
    unposed = CameraInfo(cameras[0].id, cameras[0].depth_intrinsics)
    with pytest.raises(ValueError, match="world_from_depth"):
        encode_preview(depth, {}, [unposed], 0, 0.0)
    with pytest.raises(ValueError, match="no depth image"):
        encode_preview({}, {}, cameras, 0, 0.0)
    with pytest.raises(ValueError, match="intrinsics"):
        encode_preview({cameras[0].id: depth[cameras[0].id][:, :-1]}, {}, cameras[:1], 0, 0.0)


def _with_header(header: object, body: bytes = b"", length: int | None = None) -> bytes:
    text = json.dumps(header).encode()
    return struct.pack("<I", len(text) if length is None else length) + text + body


GOOD = {"format": "volumesh.preview/1", "frame_index": 1, "captured_at": 2.0, "points": 1}


@pytest.mark.parametrize(("data", "complaint"), [
    (b"", "too short"),
    (b"\x01\x00", "too short"),
    (struct.pack("<I", 5000) + b"{}", "at most 4096"),
    (struct.pack("<I", 100) + b"{}", "shorter than"),
    (struct.pack("<I", 2) + b"\xff\xfe", "UTF-8 JSON"),
    (struct.pack("<I", 3) + b"{x}", "UTF-8 JSON"),
    (_with_header([1, 2]), "not a JSON object"),
    (_with_header({**GOOD, "format": "volumesh.preview/2"}, b"\0" * 15), "format"),
    (_with_header({**GOOD, "frame_index": -1}, b"\0" * 15), "frame_index"),
    (_with_header({**GOOD, "frame_index": True}, b"\0" * 15), "frame_index"),
    (_with_header({**GOOD, "points": "1"}, b"\0" * 15), "points"),
    (_with_header({**GOOD, "captured_at": None}, b"\0" * 15), "captured_at"),
    (_with_header({**GOOD, "points": MAX_POINTS + 1}), "at most 200000"),
    (_with_header(GOOD, b"\0" * 14), "exactly"),
    (_with_header(GOOD, b"\0" * 16), "exactly"),
    (_with_header(GOOD, struct.pack("<3f", math.nan, 0, 0) + b"\0\0\0"), "NaN"),
])
def test_malformed_buffers_are_refused(data: bytes, complaint: str) -> None:
    with pytest.raises(ValueError, match=complaint):
        decode_preview(data)
