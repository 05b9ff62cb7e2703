"""A frame-set's zip as the stream takes it: depth back bit for bit, colour as JPEG (a
recording's JPEG untouched), a preview when asked; the preview's inputs in metres."""

from __future__ import annotations

import io
import zipfile
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np
import pytest

from agent.framesets import encode_frame_set, preview_inputs
from agent.preview import decode_preview, encode_preview
from pipeline.capture import CameraInfo, Intrinsics
from pipeline.io.capture_io import StoredFiles, StoredView

SMALL = Intrinsics(width=64, height=48, fx=50.0, fy=50.0, cx=31.5, cy=23.5)
COLOR = Intrinsics(width=128, height=96, fx=100.0, fy=100.0, cx=63.5, cy=47.5)


def _depth(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    depth = rng.integers(0, 65536, size=(48, 64), dtype=np.uint16)
    depth[::7] = 0  # holes
    return depth


def _rgb(height: int, width: int, seed: int) -> np.ndarray:
    y, x = np.mgrid[0:height, 0:width]
    return np.stack([x * 2 % 256, y * 2 % 256, np.full_like(x, 40 * seed)], -1).astype(np.uint8)


def _views() -> tuple[StoredView, ...]:
    plain = CameraInfo("a", SMALL)
    registered = CameraInfo("b", SMALL)
    jpeg_camera = CameraInfo("c", SMALL, color_intrinsics=COLOR, color_from_depth=np.eye(4))
    ok, jpeg = cv2.imencode(".jpg", _rgb(96, 128, 3)[:, :, ::-1])
    assert ok
    return (StoredView(plain, 0, _depth(1)),
            StoredView(registered, 0, _depth(2), color_rgb=_rgb(48, 64, 2)),
            StoredView(jpeg_camera, 0, _depth(3).astype(">u2"), color_jpeg=jpeg.tobytes()))


@pytest.mark.parametrize("threads", [0, 3])
def test_a_frame_set_decodes_back_with_lossless_depth(threads: int) -> None:
    views = _views()
    pool = ThreadPoolExecutor(threads) if threads else None
    data = encode_frame_set(views, 42, pool=pool)
    archive = zipfile.ZipFile(io.BytesIO(data))
    assert sorted(archive.namelist()) == [
        "a/depth/000042.png", "b/color/000042.jpg", "b/depth/000042.png",
        "c/color/000042.jpg", "c/depth/000042.png"]
    assert all(info.compress_type == zipfile.ZIP_STORED for info in archive.infolist())
    for view in views:
        png = np.frombuffer(archive.read(f"{view.camera.id}/depth/000042.png"), np.uint8)
        depth = cv2.imdecode(png, cv2.IMREAD_UNCHANGED)
        assert depth.dtype == np.uint16
        np.testing.assert_array_equal(depth, view.depth_units)  # big-endian input too
    assert archive.read("c/color/000042.jpg") == views[2].color_jpeg  # passed on as recorded
    color = cv2.imdecode(np.frombuffer(archive.read("b/color/000042.jpg"), np.uint8),
                         cv2.IMREAD_COLOR)[:, :, ::-1]
    assert np.abs(color.astype(int) - views[1].color_rgb.astype(int)).mean() < 3  # JPEG, RGB
    if pool is not None:
        pool.shutdown()


def test_a_capture_s_files_go_on_as_stored_under_the_stream_s_index() -> None:
    camera = CameraInfo("d", SMALL)
    depth_png = cv2.imencode(".png", _depth(4))[1].tobytes()
    color_png = cv2.imencode(".png", _rgb(48, 64, 1))[1].tobytes()
    color_jpeg = cv2.imencode(".jpg", _rgb(48, 64, 1))[1].tobytes()
    data = encode_frame_set([StoredFiles(camera, 3, depth_png, color_png, ".png")], 9)
    archive = zipfile.ZipFile(io.BytesIO(data))
    assert {n: archive.read(n) for n in archive.namelist()} == {
        "d/depth/000009.png": depth_png, "d/color/000009.png": color_png}
    data = encode_frame_set([StoredFiles(camera, 3, depth_png, color_jpeg, ".jpeg")], 9)
    assert zipfile.ZipFile(io.BytesIO(data)).namelist() == ["d/depth/000009.png",
                                                            "d/color/000009.jpg"]
    depth_m, colors, _ = preview_inputs([StoredFiles(camera, 3, depth_png, color_png, ".png")],
                                        [camera], 0.001)
    np.testing.assert_allclose(depth_m["d"], _depth(4) * 0.001, rtol=1e-6)
    assert colors["d"] is not None
    np.testing.assert_array_equal(colors["d"], _rgb(48, 64, 1)[:, :, ::-1])  # BGR file -> RGB


def test_preview_inputs_are_metres_rgb_and_posed_cameras_fit_for_the_encoder() -> None:
    views = _views()
    pose = np.eye(4)
    pose[:3, 3] = (0.0, 1.0, 2.0)
    posed = [CameraInfo(v.camera.id, v.camera.depth_intrinsics, v.camera.color_intrinsics,
                        v.camera.color_from_depth, world_from_depth=pose) for v in views]
    depth_m, colors, cameras = preview_inputs(views, posed, 0.001)
    assert depth_m["a"].dtype == np.float32
    np.testing.assert_allclose(depth_m["c"], views[2].depth_units.astype(np.float64) * 0.001,
                               rtol=1e-6)
    assert colors["a"] is None and colors["b"] is views[1].color_rgb
    # The JPEG is decoded at a quarter of each side, its intrinsics scaled to match.
    assert colors["c"] is not None and colors["c"].shape == (24, 32, 3)
    scaled = cameras[2].color_intrinsics
    assert scaled is not None and (scaled.width, scaled.height) == (32, 24)
    assert scaled.fx == pytest.approx(25.0) and scaled.cx == pytest.approx(15.5)
    assert all(c.world_from_depth is pose for c in cameras)
    preview = decode_preview(encode_preview(depth_m, colors, cameras, 7, 1.5))
    assert preview.frame_index == 7 and len(preview.positions_m) > 0
