"""Capture reader and writer: round trips, and every kind of broken capture is refused clearly."""

from __future__ import annotations

import json
import shutil
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.capture import CameraInfo, CaptureMeta, FrameInfo, Intrinsics, View
from pipeline.io.capture_io import ArchiveLimits, open_capture, write_capture, zip_capture

WIDTH, HEIGHT = 16, 12


def _meta(camera_ids: tuple[str, ...] = ("cam0", "cam1"), frames: int = 2) -> CaptureMeta:
    intr = Intrinsics(WIDTH, HEIGHT, 20.0, 20.0, 8.0, 6.0)
    pose = np.eye(4)
    cameras = tuple(CameraInfo(id=c, depth_intrinsics=intr, world_from_depth=pose)
                    for c in camera_ids)
    return CaptureMeta(depth_scale=0.001, cameras=cameras,
                       frames=tuple(FrameInfo(i, i * 33_333) for i in range(frames)))


def _views(meta: CaptureMeta, seed: int = 0) -> list[View]:
    rng = np.random.default_rng(seed)
    views = []
    for cam in meta.cameras:
        for frame in meta.frame_indices:
            depth = rng.uniform(0.5, 3.0, (HEIGHT, WIDTH)).astype(np.float32)
            depth[0, 0] = 0.0
            color = rng.integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8)
            views.append(View(camera=cam, frame_index=frame, depth_m=depth, color_rgb=color))
    return views


@pytest.fixture
def capture_dir(tmp_path: Path) -> Path:
    meta = _meta()
    write_capture(tmp_path / "cap", meta, _views(meta))
    return tmp_path / "cap"


def test_round_trip_keeps_depth_to_a_millimetre_and_colour_exactly(tmp_path: Path) -> None:
    meta = _meta()
    views = _views(meta)
    write_capture(tmp_path / "cap", meta, views)
    with open_capture(tmp_path / "cap") as reader:
        assert reader.meta.camera_ids == ("cam0", "cam1")
        assert reader.meta.frame_indices == (0, 1)
        got = reader.read_view("cam1", 1)
    want = views[3]
    assert np.max(np.abs(got.depth_m - want.depth_m)) <= 0.0005 + 1e-6
    assert got.depth_m[0, 0] == 0.0
    assert got.color_rgb is not None and want.color_rgb is not None
    np.testing.assert_array_equal(got.color_rgb, want.color_rgb)


@pytest.mark.parametrize("top_folder", [False, True])
def test_zip_reads_like_the_directory(capture_dir: Path, tmp_path: Path, top_folder: bool) -> None:
    zip_path = tmp_path / "cap.zip"
    if top_folder:
        with zipfile.ZipFile(zip_path, "w") as archive:
            for f in capture_dir.rglob("*"):
                if f.is_file():
                    archive.write(f, "take-01/" + f.relative_to(capture_dir).as_posix())
    else:
        zip_capture(capture_dir, zip_path)
    with open_capture(zip_path) as from_zip, open_capture(capture_dir) as from_dir:
        assert from_zip.meta.camera_ids == from_dir.meta.camera_ids
        frame_zip = from_zip.read_frame(1)
        frame_dir = from_dir.read_frame(1)
    for a, b in zip(frame_zip, frame_dir, strict=True):
        np.testing.assert_array_equal(a.depth_m, b.depth_m)


def test_jpeg_colour_and_capture_without_colour_are_accepted(capture_dir: Path) -> None:
    png = capture_dir / "cam0" / "color" / "000000.png"
    image = cv2.imread(str(png))
    cv2.imwrite(str(png.with_suffix(".jpg")), image)
    png.unlink()
    shutil.rmtree(capture_dir / "cam1" / "color")
    with open_capture(capture_dir) as reader:
        assert reader.read_view("cam0", 0).color_rgb is not None
        assert reader.read_view("cam1", 0).color_rgb is None


@settings(max_examples=25, deadline=None)
@given(depth_mm=st.lists(st.integers(0, 65535), min_size=WIDTH * HEIGHT,
                         max_size=WIDTH * HEIGHT))
def test_stored_units_survive_any_value(tmp_path_factory: pytest.TempPathFactory,
                                        depth_mm: list[int]) -> None:
    meta = _meta(("c",), frames=1)
    depth = (np.array(depth_mm, np.float32).reshape(HEIGHT, WIDTH) * 0.001).astype(np.float32)
    out = tmp_path_factory.mktemp("cap")
    write_capture(out, meta, [View(meta.cameras[0], 0, depth, None)])
    with open_capture(out) as reader:
        back = reader.read_view("c", 0).depth_m
    np.testing.assert_array_equal(np.rint(back / 0.001), np.array(depth_mm).reshape(HEIGHT, WIDTH))


# --- broken captures: each must be refused with a message naming what is wrong -------------

def _edit_json(edit: Callable[[dict[str, Any]], None]) -> Callable[[Path], Path]:
    def apply(cap: Path) -> Path:
        doc = json.loads((cap / "capture.json").read_text())
        edit(doc)
        (cap / "capture.json").write_text(json.dumps(doc))
        return cap
    return apply


def _set(path: str, value: Any) -> Callable[[Path], Path]:
    def edit(doc: dict[str, Any]) -> None:
        keys: list[Any] = [int(k) if k.isdigit() else k for k in path.split(".")]
        target: Any = doc
        for key in keys[:-1]:
            target = target[key]
        if value is _DELETE:
            del target[keys[-1]]
        else:
            target[keys[-1]] = value
    return _edit_json(edit)


_DELETE = object()


def _write_file(rel: str, data: bytes) -> Callable[[Path], Path]:
    def apply(cap: Path) -> Path:
        (cap / rel).parent.mkdir(parents=True, exist_ok=True)
        (cap / rel).write_bytes(data)
        return cap
    return apply


def _jpeg_cut_short(rel_png: str) -> Callable[[Path], Path]:
    """The colour PNG ``rel_png`` as a JPEG whose last third is missing."""
    def apply(cap: Path) -> Path:
        png = cap / rel_png
        data = cv2.imencode(".jpg", cv2.imread(str(png)))[1].tobytes()
        png.with_suffix(".jpg").write_bytes(data[: len(data) * 2 // 3])
        png.unlink()
        return cap
    return apply


def _image(rel: str, image: np.ndarray) -> Callable[[Path], Path]:
    return _write_file(rel, cv2.imencode(".png", image)[1].tobytes())


def _remove(rel: str) -> Callable[[Path], Path]:
    def apply(cap: Path) -> Path:
        target = cap / rel
        shutil.rmtree(target) if target.is_dir() else target.unlink()
        return cap
    return apply


def _zip_with(entries: dict[str, bytes], compression: int = zipfile.ZIP_STORED
              ) -> Callable[[Path], Path]:
    def apply(cap: Path) -> Path:
        zip_path = cap.parent / "bad.zip"
        with zipfile.ZipFile(zip_path, "w", compression=compression) as archive:
            for f in cap.rglob("*"):
                if f.is_file():
                    archive.write(f, f.relative_to(cap).as_posix())
            for name, data in entries.items():
                archive.writestr(zipfile.ZipInfo(name), data)
        return zip_path
    return apply


def _truncated_zip(cap: Path) -> Path:
    zip_path = cap.parent / "cap.zip"
    zip_capture(cap, zip_path)
    data = zip_path.read_bytes()
    zip_path.write_bytes(data[: len(data) // 2])
    return zip_path


def _zip_bomb(cap: Path) -> Path:
    zip_path = cap.parent / "bomb.zip"
    with zipfile.ZipFile(zip_path, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("capture.json", (cap / "capture.json").read_text())
        archive.writestr("cam0/depth/junk.bin", b"\0" * (64 * 1024 * 1024))
    return zip_path


def _not_a_capture(cap: Path) -> Path:
    path = cap.parent / "notes.txt"
    path.write_text("hello")
    return path


DEPTH_8BIT = np.zeros((HEIGHT, WIDTH), np.uint8)
DEPTH_RGB16 = np.zeros((HEIGHT, WIDTH, 3), np.uint16)
DEPTH_WRONG_SIZE = np.zeros((HEIGHT + 1, WIDTH), np.uint16)

BROKEN: dict[str, tuple[Callable[[Path], Path], str]] = {
    "missing capture.json": (_remove("capture.json"), "capture.json: missing"),
    "capture.json not JSON": (_write_file("capture.json", b"{nope"), "not valid JSON"),
    "capture.json not an object": (_write_file("capture.json", b"[1, 2]"), "must be an object"),
    "unknown format version": (_set("format", "volumesh.capture/9"), "unknown format"),
    "missing depth_scale": (_set("depth_scale", _DELETE), "depth_scale: is missing"),
    "negative depth_scale": (_set("depth_scale", -1), "depth_scale: must be positive"),
    "no cameras": (_set("cameras", []), "cameras: must not be empty"),
    "bad camera id": (_set("cameras.0.id", "../etc"), "cameras[0].id"),
    "duplicate camera ids": (_set("cameras.1.id", "cam0"), "camera ids repeat"),
    "NaN intrinsics": (_set("cameras.0.depth_intrinsics.fx", float("nan")),
                       "depth_intrinsics.fx: must be finite"),
    "zero focal length": (_set("cameras.0.depth_intrinsics.fy", 0), "fy: must be positive"),
    "missing width": (_set("cameras.1.depth_intrinsics.width", _DELETE), "width: is missing"),
    "too much distortion": (_set("cameras.0.depth_intrinsics.distortion", [0.0] * 9),
                            "distortion: has 9 values"),
    "non-rigid pose": (_set("cameras.0.world_from_depth",
                            [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]),
                       "world_from_depth: is not rigid"),
    "non-finite pose": (_set("cameras.0.world_from_depth.0.3", float("inf")),
                        "world_from_depth[0][3]: must be finite"),
    "pose not 4x4": (_set("cameras.0.world_from_depth", [[1, 0, 0], [0, 1, 0], [0, 0, 1]]),
                     "must be a 4x4"),
    "colour intrinsics without transform": (
        _set("cameras.0.color_intrinsics",
             {"width": 32, "height": 24, "fx": 30, "fy": 30, "cx": 16, "cy": 12}),
        "color_intrinsics and color_from_depth"),
    "duplicate frame": (_set("frames", [{"index": 0}, {"index": 0}]), "listed twice"),
    "no frames": (_set("frames", []), "frames: must not be empty"),
    "unknown dictionary": (_set("target", {"boards": [
        {"dictionary": "DICT_9X9_7", "squares_x": 5, "squares_y": 5, "square_length_m": 0.1,
         "marker_length_m": 0.07}]}), "unknown ArUco dictionary"),
    "camera folder missing": (_remove("cam1"), "cam1/: folder missing"),
    "unlisted camera folder": (_image("cam9/depth/000000.png", np.zeros((2, 2), np.uint16)),
                               "cam9 hold depth images but are not listed"),
    "missing frame": (_remove("cam0/depth/000001.png"), "cam0/depth/000001.png: missing"),
    "8-bit depth": (_image("cam0/depth/000000.png", DEPTH_8BIT), "16-bit single-channel"),
    "3-channel depth": (_image("cam1/depth/000001.png", DEPTH_RGB16), "16-bit single-channel"),
    "depth size differs": (_image("cam0/depth/000000.png", DEPTH_WRONG_SIZE),
                           "image is 16x13 but depth_intrinsics say 16x12"),
    "colour size differs": (_image("cam1/color/000000.png", np.zeros((5, 5, 3), np.uint8)),
                            "cam1/color/000000.png: image is 5x5"),
    "depth not a PNG": (_write_file("cam0/depth/000000.png", b"GIF89a" + b"\0" * 40),
                        "not a PNG image"),
    "colour not an image": (_write_file("cam0/color/000001.jpg", b"plain text, not a jpeg"),
                            "not a JPEG or PNG"),
    "not a directory or zip": (_not_a_capture, "a capture is a directory or a .zip"),
    "truncated zip": (_truncated_zip, "not a readable zip"),
    "zip path traversal": (_zip_with({"../evil.txt": b"x"}), "path traversal"),
    "zip absolute path": (_zip_with({"/etc/evil": b"x"}), "absolute path"),
    "zip bomb": (_zip_bomb, "zip bomb"),
}


@pytest.mark.parametrize("kind", sorted(BROKEN))
def test_broken_capture_is_refused_with_a_clear_message(capture_dir: Path, kind: str) -> None:
    breaker, expected = BROKEN[kind]
    path = breaker(capture_dir)
    with pytest.raises(ValueError) as error:
        open_capture(path).close()
    assert expected in str(error.value)
    assert "\n" not in str(error.value)


def test_archive_limits_are_enforced(capture_dir: Path, tmp_path: Path) -> None:
    zip_path = tmp_path / "cap.zip"
    zip_capture(capture_dir, zip_path)
    with pytest.raises(ValueError, match="entries, more than the limit 3"):
        open_capture(zip_path, ArchiveLimits(max_files=3))
    with pytest.raises(ValueError, match="unpacks to more than 100 bytes"):
        open_capture(zip_path, ArchiveLimits(max_unpacked_bytes=100))


def test_corrupt_pixels_are_reported_when_read(capture_dir: Path) -> None:
    path = capture_dir / "cam0" / "depth" / "000001.png"
    data = path.read_bytes()
    path.write_bytes(data[:40] + b"\xff" * (len(data) - 40))
    with open_capture(capture_dir) as reader, pytest.raises(ValueError, match="000001.png"):
        reader.read_view("cam0", 1)


def test_unknown_frame_is_refused(capture_dir: Path) -> None:
    with open_capture(capture_dir) as reader, pytest.raises(ValueError, match="no frame 7"):
        reader.read_frame(7)


def test_a_jpeg_cut_short_is_refused_when_read(capture_dir: Path) -> None:
    path = _jpeg_cut_short("cam0/color/000001.png")(capture_dir)
    with open_capture(path) as reader, pytest.raises(ValueError) as error:
        reader.read_frame(1)
    assert "cam0/color/000001.jpg: image data are corrupt" in str(error.value)
