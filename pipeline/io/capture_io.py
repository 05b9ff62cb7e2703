"""Reading and writing captures in format v1: a directory, or the same tree in a zip.

`open_capture` checks everything it can without decoding pixels (capture.json, folders, files,
PNG/JPEG headers) so a broken capture is refused before any work starts; pixel data are decoded
on demand by `CaptureReader.read_view`. Every error is a ``ValueError`` naming file and field.
"""

from __future__ import annotations

import json
import os
import re
import zipfile
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from types import TracebackType

import cv2
import numpy as np
from numpy.typing import NDArray

from pipeline.capture import CAMERA_ID_PATTERN, CameraInfo, CaptureMeta, View
from pipeline.io.capture_images import (
    ImageSpec,
    check_declared_sizes,
    check_image_file,
    decode_color_rgb,
    decode_depth,
)
from pipeline.io.capture_json import meta_from_json, meta_to_json
from pipeline.io.capture_source import ArchiveLimits, DirSource, Source, open_zip
from pipeline.io.png16 import png16_parts

_COLOR_SUFFIXES = (".jpg", ".jpeg", ".png")
# Room for a million frames with timestamps; parsed, JSON takes about ten times its size.
_MAX_CAPTURE_JSON_BYTES = 64 * 1024 * 1024


def _color_path(source: Source, camera_id: str, frame: int) -> str | None:
    for suffix in _COLOR_SUFFIXES:
        path = f"{camera_id}/color/{frame:06d}{suffix}"
        if source.exists(path):
            return path
    return None


def _depth_spec(camera: CameraInfo, frame: int, max_pixels: int) -> ImageSpec:
    return ImageSpec(f"{camera.id}/depth/{frame:06d}.png", camera.depth_intrinsics,
                     "depth_intrinsics", max_pixels, depth=True)


def _color_spec(camera: CameraInfo, path: str, max_pixels: int) -> ImageSpec:
    if camera.color_intrinsics is None:  # registered to depth: same size
        return ImageSpec(path, camera.depth_intrinsics, "depth_intrinsics", max_pixels, False)
    return ImageSpec(path, camera.color_intrinsics, "color_intrinsics", max_pixels, False)


def _check_image(source: Source, spec: ImageSpec) -> None:
    check_image_file(partial(source.read_head, spec.path), source.size_bytes(spec.path), spec)


def _check_layout(source: Source, meta: CaptureMeta, max_pixels: int) -> None:
    files = source.list()
    folders = {p.split("/", 1)[0] for p in files if "/" in p}
    with_depth = {p.split("/", 1)[0] for p in files if p.count("/") >= 2
                  and p.split("/")[1] == "depth"}
    unknown = sorted(f for f in with_depth - set(meta.camera_ids)
                     if re.fullmatch(CAMERA_ID_PATTERN, f))
    if unknown:
        raise ValueError(f"capture.json: cameras: folder(s) {', '.join(unknown)} hold depth "
                         "images but are not listed as cameras")
    for cam in meta.cameras:
        if cam.id not in folders:
            raise ValueError(f"{cam.id}/: folder missing for camera {cam.id!r} in capture.json")
        for frame in meta.frame_indices:
            depth = _depth_spec(cam, frame, max_pixels)
            if not source.exists(depth.path):
                raise ValueError(f"{depth.path}: missing (frame {frame} is listed in "
                                 "capture.json)")
            _check_image(source, depth)
            color_path = _color_path(source, cam.id, frame)
            if color_path is not None:
                _check_image(source, _color_spec(cam, color_path, max_pixels))


class CaptureReader:
    """An opened, validated capture. Use as a context manager (a zip stays open)."""

    def __init__(self, source: Source, meta: CaptureMeta, name: str,
                 max_image_pixels: int = ArchiveLimits.max_image_pixels) -> None:
        self._source = source
        self.meta = meta
        self.name = name
        self.max_image_pixels = max_image_pixels

    def read_view(self, camera_id: str, frame_index: int, *, with_color: bool = True) -> View:
        """One camera at one frame: depth in metres (0 = none), colour as RGB when present."""
        camera = self.meta.camera(camera_id)
        depth = _depth_spec(camera, frame_index, self.max_image_pixels)
        raw = decode_depth(self._source.read(depth.path), depth)
        depth_m = raw.astype(np.float32) * np.float32(self.meta.depth_scale)
        del raw  # the float copy replaces it; keep one image's worth of memory, not two
        color = None
        color_path = _color_path(self._source, camera_id, frame_index) if with_color else None
        if color_path is not None:
            spec = _color_spec(camera, color_path, self.max_image_pixels)
            color = decode_color_rgb(self._source.read(color_path), spec)
        return View(camera=camera, frame_index=frame_index, depth_m=depth_m, color_rgb=color)

    def read_image_files(self, camera_id: str, frame_index: int) -> StoredFiles:
        """One camera's files at one frame as stored, undecoded (open_capture checked their
        headers): for a reader that passes them on, such as a stream's agent."""
        camera = self.meta.camera(camera_id)
        depth = _depth_spec(camera, frame_index, self.max_image_pixels)
        color_path = _color_path(self._source, camera_id, frame_index)
        color = None if color_path is None else bytes(self._source.read(color_path))
        return StoredFiles(camera, frame_index, bytes(self._source.read(depth.path)),
                           color, None if color_path is None else Path(color_path).suffix)

    def read_frame(self, frame_index: int, *, with_color: bool = True) -> list[View]:
        """Every camera's view at one frame, in capture.json's camera order."""
        if frame_index not in self.meta.frame_indices:
            raise ValueError(f"capture has no frame {frame_index}; frames: "
                             f"{list(self.meta.frame_indices)[:10]}")
        return [self.read_view(c.id, frame_index, with_color=with_color) for c in self.meta.cameras]

    def close(self) -> None:
        self._source.close()

    def __enter__(self) -> CaptureReader:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


def open_capture(path: str | Path, limits: ArchiveLimits | None = None) -> CaptureReader:
    """Opens and validates a capture directory or zip; raises ValueError naming what is wrong."""
    path = Path(path)
    limits = limits or ArchiveLimits()
    if not path.exists():
        raise ValueError(f"{path}: no such capture (directory or .zip)")
    source: Source
    if path.is_dir():
        source = DirSource(path)
    elif zipfile.is_zipfile(path) or path.suffix.lower() == ".zip":
        source = open_zip(path, limits)
    else:
        raise ValueError(f"{path.name}: a capture is a directory or a .zip archive")
    try:
        meta = _read_meta(source, limits.max_image_pixels)
        _check_layout(source, meta, limits.max_image_pixels)
    except ValueError:
        source.close()
        raise
    return CaptureReader(source, meta, path.name, limits.max_image_pixels)


def _read_meta(source: Source, max_image_pixels: int) -> CaptureMeta:
    if not source.exists("capture.json"):
        raise ValueError("capture.json: missing at the top of the capture")
    if source.size_bytes("capture.json") > _MAX_CAPTURE_JSON_BYTES:
        raise ValueError(f"capture.json: {source.size_bytes('capture.json')} bytes, more than "
                         f"the {_MAX_CAPTURE_JSON_BYTES} a capture's description may take")
    try:
        document = json.loads(source.read("capture.json"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"capture.json: not valid JSON ({exc})") from None
    except RecursionError:  # json nests deeper than Python's stack allows
        raise ValueError("capture.json: nested too deeply") from None
    meta = meta_from_json(document)
    check_declared_sizes(meta, max_image_pixels)
    return meta


def _encode_png(image: NDArray[np.integer], where: str) -> bytes:
    ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise ValueError(f"{where}: could not encode image")
    return buf.tobytes()


def depth_to_units(depth_m: NDArray[np.floating], depth_scale: float) -> NDArray[np.uint16]:
    """Metres to stored units: round to the scale, 0 stays 0, clipped to uint16."""
    units = np.rint(np.nan_to_num(depth_m, nan=0.0) / depth_scale)
    return np.clip(units, 0, np.iinfo(np.uint16).max).astype(np.uint16)


@dataclass(frozen=True)
class StoredFiles:
    """One camera's image files at one frame, as a capture stores them."""

    camera: CameraInfo
    frame_index: int
    depth_png: bytes
    """16-bit greyscale PNG, depth in the capture's units."""
    color: bytes | None = None
    color_suffix: str | None = None
    """.jpg, .jpeg or .png; None without colour."""


@dataclass(frozen=True)
class StoredView:
    """One camera's images at one frame as the capture stores them, for a source whose data
    are in that form already (a recording's millimetres and JPEGs): written with no
    conversion. A :class:`View` is converted to this on the way out."""

    camera: CameraInfo
    frame_index: int
    depth_units: NDArray[np.uint16]
    """(H, W) depth in the capture's units (value × depth_scale = metres), 0 = none."""
    color_rgb: NDArray[np.uint8] | None = None
    """(Hc, Wc, 3) RGB, written as PNG."""
    color_jpeg: bytes | None = None
    """A JPEG file's bytes, written as they are (instead of ``color_rgb``)."""

    def __post_init__(self) -> None:
        if self.color_rgb is not None and self.color_jpeg is not None:
            raise ValueError(f"{self.camera.id} frame {self.frame_index}: colour given both "
                             "as RGB and as a JPEG")


def stored_view(view: View | StoredView, depth_scale: float) -> StoredView:
    """The view as stored in a capture of ``depth_scale`` metres per depth unit."""
    if isinstance(view, StoredView):
        return view
    return StoredView(view.camera, view.frame_index, depth_to_units(view.depth_m, depth_scale),
                      color_rgb=view.color_rgb)


def _write_view(out: Path, view: StoredView, folders: set[Path]) -> None:
    """Writes the view's files; ``folders`` are those known to exist (one mkdir each)."""
    cam_dir = out / view.camera.id
    name = f"{view.frame_index:06d}"
    _write_file(cam_dir / "depth" / f"{name}.png", png16_parts(view.depth_units), folders)
    if view.color_jpeg is not None:
        _write_file(cam_dir / "color" / f"{name}.jpg", (view.color_jpeg,), folders)
    elif view.color_rgb is not None:
        bgr = np.ascontiguousarray(view.color_rgb[:, :, ::-1])
        color_png = _encode_png(bgr, f"{view.camera.id}/color/{name}.png")
        _write_file(cam_dir / "color" / f"{name}.png", (color_png,), folders)


def _write_file(path: Path, parts: Sequence[bytes | memoryview], folders: set[Path]) -> None:
    """Writes ``parts`` one after another as the file's bytes, replacing any file there.
    Three system calls for a whole file (a Python file object adds a stat, an ioctl and a
    seek, and joining the parts a copy): thousands of images are written per second."""
    if path.parent not in folders:
        path.parent.mkdir(parents=True, exist_ok=True)
        folders.add(path.parent)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, 0o666)
    try:
        views = (memoryview(part).cast("B") for part in parts)
        _write_all(fd, [view for view in views if len(view)])
    finally:
        os.close(fd)


def _write_all(fd: int, pending: list[memoryview]) -> None:
    """os.writev until every byte is written: it may write fewer than asked (a signal, a
    nearly full disk), and then ends with an OSError where nothing more fits."""
    while pending:
        written = os.writev(fd, pending)
        if written == 0:
            raise OSError(f"nothing written to file descriptor {fd}")
        while pending and written >= len(pending[0]):
            written -= len(pending.pop(0))
        if pending:
            pending[0] = pending[0][written:]


def write_capture(out_dir: str | Path, meta: CaptureMeta,
                  views: Iterable[View | StoredView]) -> None:
    """Writes capture.json and each view's depth (16-bit PNG) and colour (PNG, or the JPEG a
    StoredView carries). A View's depth in metres is rounded to ``meta.depth_scale``; a
    StoredView's must be in those units already."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "capture.json").write_text(json.dumps(meta_to_json(meta), indent=1))
    folders: set[Path] = set()
    for view in views:
        _write_view(out, stored_view(view, meta.depth_scale), folders)


def zip_capture(capture_dir: str | Path, zip_path: str | Path) -> None:
    """Packs a capture directory into a zip with its files at the top level."""
    root = Path(capture_dir)
    with zipfile.ZipFile(zip_path, "w", compression=zipfile.ZIP_STORED) as archive:
        for file in sorted(root.rglob("*")):
            if file.is_file():
                archive.write(file, file.relative_to(root).as_posix())


def camera_center_world(camera: CameraInfo) -> NDArray[np.float64]:
    """(3,) depth camera centre in the world, metres."""
    if camera.world_from_depth is None:
        raise ValueError(f"camera {camera.id!r} has no world_from_depth (calibrate the rig first)")
    return np.asarray(camera.world_from_depth)[:3, 3].copy()
