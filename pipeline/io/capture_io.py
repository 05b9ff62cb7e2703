"""Reading and writing captures in format v1: a directory, or the same tree in a zip.

`open_capture` checks everything it can without decoding pixels (capture.json, folders, files,
PNG/JPEG headers) so a broken capture is refused before any work starts; pixel data are decoded
on demand by `CaptureReader.read_view`. Every error is a ``ValueError`` naming file and field.
"""

from __future__ import annotations

import json
import re
import struct
import zipfile
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from types import TracebackType

import cv2
import numpy as np
from numpy.typing import NDArray

from pipeline.capture import CAMERA_ID_PATTERN, CameraInfo, CaptureMeta, Intrinsics, View
from pipeline.io.capture_json import meta_from_json, meta_to_json

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_COLOR_SUFFIXES = (".jpg", ".jpeg", ".png")


@dataclass(frozen=True)
class ArchiveLimits:
    """Limits that keep a hostile zip from exhausting memory or disk."""

    max_files: int = 200_000
    """Most entries a capture zip may hold."""
    max_unpacked_bytes: int = 16 * 1024**3
    """Largest total uncompressed size, bytes."""
    max_compression_ratio: float = 200.0
    """Largest uncompressed/compressed ratio of one entry (zip bombs go far beyond)."""


class _Source:
    """Files of a capture, wherever they live; paths are POSIX and relative to the root."""

    def read(self, path: str) -> bytes:
        raise NotImplementedError

    def read_head(self, path: str, size: int) -> bytes:
        return self.read(path)[:size]

    def exists(self, path: str) -> bool:
        raise NotImplementedError

    def list(self) -> list[str]:
        raise NotImplementedError

    def close(self) -> None:
        """Directories hold nothing open."""


class _DirSource(_Source):
    def __init__(self, root: Path) -> None:
        self.root = root

    def read(self, path: str) -> bytes:
        return (self.root / path).read_bytes()

    def read_head(self, path: str, size: int) -> bytes:
        with open(self.root / path, "rb") as f:
            return f.read(size)

    def exists(self, path: str) -> bool:
        return (self.root / path).is_file()

    def list(self) -> list[str]:
        return [p.relative_to(self.root).as_posix() for p in self.root.rglob("*") if p.is_file()]


class _ZipSource(_Source):
    def __init__(self, archive: zipfile.ZipFile, prefix: str, names: list[str]) -> None:
        self.archive = archive
        self.prefix = prefix
        self.names = {n[len(prefix):] for n in names if n.startswith(prefix)}

    def read(self, path: str) -> bytes:
        return self.archive.read(self.prefix + path)

    def read_head(self, path: str, size: int) -> bytes:
        with self.archive.open(self.prefix + path) as f:
            return f.read(size)

    def exists(self, path: str) -> bool:
        return path in self.names

    def list(self) -> list[str]:
        return sorted(self.names)

    def close(self) -> None:
        self.archive.close()


def _open_zip(path: Path, limits: ArchiveLimits) -> _ZipSource:
    try:
        archive = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError) as exc:
        raise ValueError(f"{path.name}: not a readable zip archive ({exc})") from None
    infos = archive.infolist()
    if len(infos) > limits.max_files:
        raise ValueError(f"{path.name}: {len(infos)} entries, more than the limit "
                         f"{limits.max_files}")
    total = 0
    names = []
    for info in infos:
        name = info.filename
        parts = PurePosixPath(name).parts
        if name.startswith(("/", "\\")) or re.match(r"^[A-Za-z]:", name) or "\\" in name:
            raise ValueError(f"{path.name}: entry {name!r} has an absolute path")
        if ".." in parts:
            raise ValueError(f"{path.name}: entry {name!r} escapes the archive (path traversal)")
        if info.is_dir():
            continue
        total += info.file_size
        if total > limits.max_unpacked_bytes:
            raise ValueError(f"{path.name}: unpacks to more than {limits.max_unpacked_bytes} bytes")
        if info.file_size > 1024 * 1024 and (
                info.file_size > limits.max_compression_ratio * max(info.compress_size, 1)):
            raise ValueError(f"{path.name}: entry {name!r} is compressed over "
                             f"{limits.max_compression_ratio:.0f}:1 (zip bomb?)")
        names.append(name)
    if "capture.json" in names:
        prefix = ""
    else:
        tops = [n for n in names if n.count("/") == 1 and n.endswith("/capture.json")]
        if len(tops) != 1:
            archive.close()
            raise ValueError(f"{path.name}: no capture.json at the top (or under one top folder)")
        prefix = tops[0][: -len("capture.json")]
    return _ZipSource(archive, prefix, names)


def _png_header(head: bytes, where: str) -> tuple[int, int, int, int]:
    """(width, height, bit depth, colour type) from a PNG's IHDR chunk."""
    if len(head) < 26 or head[:8] != _PNG_SIGNATURE or head[12:16] != b"IHDR":
        raise ValueError(f"{where}: not a PNG image")
    width, height, bit_depth, color_type = struct.unpack(">IIBB", head[16:26])
    return width, height, bit_depth, color_type


def _check_depth_file(source: _Source, path: str, intr: Intrinsics) -> None:
    width, height, bit_depth, color_type = _png_header(source.read_head(path, 33), path)
    if bit_depth != 16 or color_type != 0:
        raise ValueError(f"{path}: depth must be a 16-bit single-channel PNG, "
                         f"got bit depth {bit_depth}, PNG colour type {color_type}")
    if (width, height) != (intr.width, intr.height):
        raise ValueError(f"{path}: image is {width}x{height} but depth_intrinsics say "
                         f"{intr.width}x{intr.height}")


def _image_size(data: bytes, where: str) -> tuple[int, int]:
    if data[:8] == _PNG_SIGNATURE:
        width, height, _, _ = _png_header(data, where)
        return width, height
    if data[:2] != b"\xff\xd8":
        raise ValueError(f"{where}: not a JPEG or PNG image")
    # Walk the JPEG markers to the start-of-frame segment, which holds the size.
    i = 2
    while i + 9 < len(data):
        if data[i] != 0xFF:
            break
        marker = data[i + 1]
        seg_len = struct.unpack(">H", data[i + 2:i + 4])[0]
        if marker in (0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF):
            height, width = struct.unpack(">HH", data[i + 5:i + 9])
            return width, height
        i += 2 + seg_len
    raise ValueError(f"{where}: JPEG has no readable frame header")


def _color_path(source: _Source, camera_id: str, frame: int) -> str | None:
    for suffix in _COLOR_SUFFIXES:
        path = f"{camera_id}/color/{frame:06d}{suffix}"
        if source.exists(path):
            return path
    return None


def _check_layout(source: _Source, meta: CaptureMeta) -> None:
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
        color_intr = cam.color_intrinsics or cam.depth_intrinsics
        for frame in meta.frame_indices:
            depth_path = f"{cam.id}/depth/{frame:06d}.png"
            if not source.exists(depth_path):
                raise ValueError(f"{depth_path}: missing (frame {frame} is listed in capture.json)")
            _check_depth_file(source, depth_path, cam.depth_intrinsics)
            color_path = _color_path(source, cam.id, frame)
            if color_path is not None:
                width, height = _image_size(source.read_head(color_path, 65536), color_path)
                if (width, height) != (color_intr.width, color_intr.height):
                    which = "color_intrinsics" if cam.color_intrinsics else "depth_intrinsics"
                    raise ValueError(f"{color_path}: image is {width}x{height} but {which} say "
                                     f"{color_intr.width}x{color_intr.height}")


class CaptureReader:
    """An opened, validated capture. Use as a context manager (a zip stays open)."""

    def __init__(self, source: _Source, meta: CaptureMeta, name: str) -> None:
        self._source = source
        self.meta = meta
        self.name = name

    def read_view(self, camera_id: str, frame_index: int, *, with_color: bool = True) -> View:
        """One camera at one frame: depth in metres (0 = none), colour as RGB when present."""
        camera = self.meta.camera(camera_id)
        depth_path = f"{camera_id}/depth/{frame_index:06d}.png"
        raw = _decode(self._source.read(depth_path), cv2.IMREAD_UNCHANGED, depth_path)
        if raw.dtype != np.uint16 or raw.ndim != 2:
            raise ValueError(f"{depth_path}: depth must be a 16-bit single-channel PNG")
        depth_m = raw.astype(np.float32) * np.float32(self.meta.depth_scale)
        color = None
        color_path = _color_path(self._source, camera_id, frame_index) if with_color else None
        if color_path is not None:
            bgr = _decode(self._source.read(color_path), cv2.IMREAD_COLOR, color_path)
            color = np.ascontiguousarray(bgr[:, :, ::-1])
        return View(camera=camera, frame_index=frame_index, depth_m=depth_m, color_rgb=color)

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


def _decode(data: bytes, flags: int, where: str) -> NDArray[np.generic]:
    image = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    if image is None:
        raise ValueError(f"{where}: image data are corrupt")
    return image


def open_capture(path: str | Path, limits: ArchiveLimits | None = None) -> CaptureReader:
    """Opens and validates a capture directory or zip; raises ValueError naming what is wrong."""
    path = Path(path)
    if not path.exists():
        raise ValueError(f"{path}: no such capture (directory or .zip)")
    source: _Source
    if path.is_dir():
        source = _DirSource(path)
    elif zipfile.is_zipfile(path) or path.suffix.lower() == ".zip":
        source = _open_zip(path, limits or ArchiveLimits())
    else:
        raise ValueError(f"{path.name}: a capture is a directory or a .zip archive")
    try:
        if not source.exists("capture.json"):
            raise ValueError("capture.json: missing at the top of the capture")
        try:
            document = json.loads(source.read("capture.json"))
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise ValueError(f"capture.json: not valid JSON ({exc})") from None
        meta = meta_from_json(document)
        _check_layout(source, meta)
    except (ValueError, zipfile.BadZipFile, OSError, EOFError) as exc:
        source.close()
        raise ValueError(str(exc)) from None
    return CaptureReader(source, meta, path.name)


def _encode_png(image: NDArray[np.integer], where: str) -> bytes:
    ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise ValueError(f"{where}: could not encode image")
    return buf.tobytes()


def depth_to_units(depth_m: NDArray[np.floating], depth_scale: float) -> NDArray[np.uint16]:
    """Metres to stored units: round to the scale, 0 stays 0, clipped to uint16."""
    units = np.rint(np.nan_to_num(depth_m, nan=0.0) / depth_scale)
    return np.clip(units, 0, np.iinfo(np.uint16).max).astype(np.uint16)


def write_capture(out_dir: str | Path, meta: CaptureMeta, views: Iterable[View]) -> None:
    """Writes capture.json and each view's depth (16-bit PNG) and colour (PNG)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "capture.json").write_text(json.dumps(meta_to_json(meta), indent=1))
    for view in views:
        cam_dir = out / view.camera.id
        name = f"{view.frame_index:06d}.png"
        (cam_dir / "depth").mkdir(parents=True, exist_ok=True)
        depth = depth_to_units(view.depth_m, meta.depth_scale)
        (cam_dir / "depth" / name).write_bytes(_encode_png(depth, f"{view.camera.id}/depth/{name}"))
        if view.color_rgb is not None:
            (cam_dir / "color").mkdir(parents=True, exist_ok=True)
            bgr = np.ascontiguousarray(view.color_rgb[:, :, ::-1])
            color_png = _encode_png(bgr, f"{view.camera.id}/color/{name}")
            (cam_dir / "color" / name).write_bytes(color_png)


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
