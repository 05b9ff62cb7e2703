"""The capture writer given depth in its stored units: written as given, read back exactly."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from numpy.typing import NDArray
from PIL import Image

from pipeline.capture import CameraInfo, CaptureMeta, FrameInfo, Intrinsics, View
from pipeline.io.capture_io import StoredView, open_capture, write_capture

WIDTH, HEIGHT = 16, 12
SCALE_M = 0.001


def _meta() -> CaptureMeta:
    camera = CameraInfo(id="cam0", depth_intrinsics=Intrinsics(WIDTH, HEIGHT, 20.0, 20.0, 8.0,
                                                                6.0))
    return CaptureMeta(depth_scale=SCALE_M, cameras=(camera,),
                       frames=(FrameInfo(0, 0), FrameInfo(1, 33_333)))


@settings(max_examples=40, deadline=None)
@given(units=arrays(st.sampled_from([np.dtype("<u2"), np.dtype(">u2")]), (HEIGHT, WIDTH),
                    elements=st.one_of(st.sampled_from([0, 65535]), st.integers(0, 65535))))
def test_stored_units_are_written_as_given_and_read_back_exactly(
        tmp_path_factory: pytest.TempPathFactory, units: NDArray[np.uint16]) -> None:
    meta = _meta()
    out = tmp_path_factory.mktemp("cap")
    camera = meta.cameras[0]
    write_capture(out, meta, [StoredView(camera, 0, units), StoredView(camera, 1, units)])
    png = out / "cam0" / "depth" / "000000.png"
    np.testing.assert_array_equal(cv2.imread(str(png), cv2.IMREAD_UNCHANGED), units)
    with Image.open(png) as picture:
        np.testing.assert_array_equal(np.asarray(picture).astype(np.int64),
                                      units.astype(np.int64))
    with open_capture(out) as reader:
        depth_m = reader.read_view("cam0", 1).depth_m
    np.testing.assert_array_equal(depth_m, units.astype(np.float32) * np.float32(SCALE_M))


def test_views_in_metres_and_in_units_write_the_same_files(tmp_path: Path) -> None:
    meta = _meta()
    camera = meta.cameras[0]
    units = np.random.default_rng(0).integers(0, 8000, (HEIGHT, WIDTH)).astype(np.uint16)
    color = np.random.default_rng(1).integers(0, 256, (HEIGHT, WIDTH, 3), np.uint8)
    write_capture(tmp_path / "m", meta, [View(camera, 0, units * np.float32(SCALE_M), color)])
    write_capture(tmp_path / "u", meta, [StoredView(camera, 0, units, color_rgb=color)])
    for name in ("capture.json", "cam0/depth/000000.png", "cam0/color/000000.png"):
        assert (tmp_path / "m" / name).read_bytes() == (tmp_path / "u" / name).read_bytes()


def test_a_jpeg_is_written_as_it_is_and_read_as_the_colour(tmp_path: Path) -> None:
    meta = _meta()
    picture = np.full((HEIGHT, WIDTH, 3), (200, 40, 10), np.uint8)
    jpeg = cv2.imencode(".jpg", picture[:, :, ::-1])[1].tobytes()
    views = [StoredView(meta.cameras[0], i, np.full((HEIGHT, WIDTH), 1500, np.uint16),
                        color_jpeg=jpeg) for i in (0, 1)]
    write_capture(tmp_path, meta, views)
    assert (tmp_path / "cam0" / "color" / "000001.jpg").read_bytes() == jpeg
    with open_capture(tmp_path) as reader:
        rgb = reader.read_view("cam0", 1).color_rgb
    assert rgb is not None and np.abs(rgb.astype(int) - picture).max() <= 8


def test_colour_given_twice_is_refused() -> None:
    camera = _meta().cameras[0]
    with pytest.raises(ValueError, match="both"):
        StoredView(camera, 0, np.zeros((HEIGHT, WIDTH), np.uint16),
                   color_rgb=np.zeros((HEIGHT, WIDTH, 3), np.uint8), color_jpeg=b"\xff\xd8")


def test_image_files_are_read_back_as_stored_without_a_decode(tmp_path: Path) -> None:
    meta = _meta()
    camera = meta.cameras[0]
    units = np.arange(WIDTH * HEIGHT, dtype=np.uint16).reshape(HEIGHT, WIDTH)
    jpeg = cv2.imencode(".jpg", np.zeros((HEIGHT, WIDTH, 3), np.uint8))[1].tobytes()
    write_capture(tmp_path, meta, [StoredView(camera, 0, units, color_jpeg=jpeg),
                                   StoredView(camera, 1, units)])
    with open_capture(tmp_path) as reader:
        first, second = (reader.read_image_files("cam0", f) for f in (0, 1))
    assert first.depth_png == (tmp_path / "cam0/depth/000000.png").read_bytes()
    assert (first.color, first.color_suffix) == (jpeg, ".jpg")
    assert (second.frame_index, second.color, second.color_suffix) == (1, None, None)
