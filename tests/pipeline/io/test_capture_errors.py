"""Damaged and hostile captures: every read error becomes a ValueError naming the file, and
images are checked against their intrinsics and the pixel cap before they are decoded."""

from __future__ import annotations

import io
import struct
import zipfile
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.io.capture_io import ArchiveLimits, CaptureReader, open_capture
from tests.hostile_captures import (
    capture_json,
    central_record,
    damaged_member_zip,
    pack,
    png_bomb,
)

WIDTH, HEIGHT = 256, 192  # members over 64 KiB, so header reads do not reach their end
DEPTH = "cam0/depth/000000.png"
COLOR = "cam0/color/000000.png"


def _entries() -> dict[str, bytes]:
    """A one-camera capture whose images are stored PNGs (deflate in the zip shrinks them)."""
    ramp = np.arange(WIDTH * HEIGHT, dtype=np.uint16).reshape(HEIGHT, WIDTH)
    colour = np.dstack([ramp % 256] * 3).astype(np.uint8)
    stored = [cv2.IMWRITE_PNG_COMPRESSION, 0]
    return {"capture.json": capture_json(WIDTH, HEIGHT),
            DEPTH: cv2.imencode(".png", ramp, stored)[1].tobytes(),
            COLOR: cv2.imencode(".png", colour, stored)[1].tobytes()}


def _read_all(path: Path, limits: ArchiveLimits | None = None) -> None:
    with open_capture(path, limits) as reader:
        for frame in reader.meta.frame_indices:
            reader.read_frame(frame)


def _refusal(path: Path, limits: ArchiveLimits | None = None) -> str:
    with pytest.raises(ValueError) as error:
        _read_all(path, limits)
    message = str(error.value)
    assert "\n" not in message
    return message


def _write(tmp_path: Path, data: bytes) -> Path:
    path = tmp_path / "capture.zip"
    path.write_bytes(data)
    return path


def test_the_undamaged_capture_reads(tmp_path: Path) -> None:
    _read_all(_write(tmp_path, pack(_entries(), zipfile.ZIP_DEFLATED)))


@pytest.mark.parametrize("how, why", [("crc", "(Bad CRC-32 for file"),
                                      ("deflate", "invalid block type)"),
                                      ("truncate", "(its stored data end early)")])
@pytest.mark.parametrize("member", ["capture.json", DEPTH, COLOR])
def test_a_damaged_member_is_refused_naming_it(tmp_path: Path, member: str, how: str,
                                               why: str) -> None:
    path = _write(tmp_path, damaged_member_zip(_entries(), member, how))
    message = _refusal(path)
    assert message.startswith(f"{member}: cannot be read ("), message
    assert why in message


def _patched(member: str, offset: int, value: int) -> bytes:
    data = bytearray(pack(_entries()))
    struct.pack_into("<H", data, central_record(data, member) + offset, value)
    return bytes(data)


@pytest.mark.parametrize("what, offset, value, why", [
    ("unknown compression method", 10, 99, "compression method"),
    ("encrypted entry", 8, 0x1, "encrypted"),
])
def test_an_unreadable_entry_is_refused_naming_it(tmp_path: Path, what: str, offset: int,
                                                  value: int, why: str) -> None:
    message = _refusal(_write(tmp_path, _patched(DEPTH, offset, value)))
    assert message.startswith(f"{DEPTH}: cannot be read") and why in message, (what, message)


def test_declared_intrinsics_over_the_pixel_cap_are_refused(tmp_path: Path) -> None:
    path = _write(tmp_path, pack(_entries()))
    message = _refusal(path, ArchiveLimits(max_image_pixels=WIDTH * HEIGHT - 1))
    assert message == (f"capture.json: cameras[0].depth_intrinsics: {WIDTH}x{HEIGHT} is "
                       f"{WIDTH * HEIGHT} pixels, over the limit of {WIDTH * HEIGHT - 1} "
                       "pixels per image")


def test_a_png_bomb_is_refused_from_its_header(tmp_path: Path) -> None:
    entries = {**_entries(), DEPTH: png_bomb(12000, 12000)}
    message = _refusal(_write(tmp_path, pack(entries)))
    assert message == (f"{DEPTH}: image is 12000x12000, 144000000 pixels, over the limit of "
                       "25000000 pixels")


def test_a_png_bomb_under_a_raised_cap_is_refused_for_its_size(tmp_path: Path) -> None:
    entries = {**_entries(), DEPTH: png_bomb(12000, 12000)}
    message = _refusal(_write(tmp_path, pack(entries)), ArchiveLimits(max_image_pixels=10**9))
    assert message == f"{DEPTH}: image is 12000x12000 but depth_intrinsics say {WIDTH}x{HEIGHT}"


def _opened_dir(tmp_path: Path) -> tuple[CaptureReader, Path]:
    folder = tmp_path / "capture"
    for name, data in _entries().items():
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).write_bytes(data)
    return open_capture(folder), folder


def test_an_image_is_checked_again_before_it_is_decoded(tmp_path: Path) -> None:
    reader, folder = _opened_dir(tmp_path)
    (folder / DEPTH).write_bytes(png_bomb(12000, 12000))  # swapped after the capture opened
    with reader, pytest.raises(ValueError, match="12000x12000, 144000000 pixels, over"):
        reader.read_view("cam0", 0)


def test_an_image_file_longer_than_its_pixels_need_is_refused_unread(tmp_path: Path) -> None:
    entries = _entries()
    entries[DEPTH] += bytes(2 * WIDTH * HEIGHT * 2 + 1024 * 1024)
    message = _refusal(_write(tmp_path, pack(entries)))
    assert message.startswith(f"{DEPTH}: the file has ") and "can need" in message


def test_corrupt_pixel_data_name_the_file(tmp_path: Path) -> None:
    entries = _entries()
    entries[COLOR] = entries[COLOR][:64] + b"\x00garbage" * 100
    assert _refusal(_write(tmp_path, pack(entries))) == f"{COLOR}: image data are corrupt"


def test_a_zip_whose_directory_is_damaged_is_refused(tmp_path: Path) -> None:
    data = bytearray(pack(_entries()))
    struct.pack_into("<I", data, central_record(data, DEPTH) + 42, 2**31)  # header offset
    message = _refusal(_write(tmp_path, bytes(data)))
    assert message.startswith(f"{DEPTH}: cannot be read"), message


def test_a_deeply_nested_capture_json_is_refused(tmp_path: Path) -> None:
    entries = {**_entries(), "capture.json": b"[" * 100_000 + b"]" * 100_000}
    assert _refusal(_write(tmp_path, pack(entries))) == "capture.json: nested too deeply"


def test_member_paths_are_named_from_the_capture_root(tmp_path: Path) -> None:
    entries = {f"take/{name}": data for name, data in _entries().items()}
    buffer = io.BytesIO(damaged_member_zip(entries, f"take/{DEPTH}", "crc"))
    assert _refusal(_write(tmp_path, buffer.getvalue())).startswith(f"{DEPTH}: cannot be read")


def test_an_outsized_capture_json_is_refused_unread(tmp_path: Path) -> None:
    reader, folder = _opened_dir(tmp_path)
    reader.close()
    with open(folder / "capture.json", "r+b") as f:
        f.truncate(64 * 1024 * 1024 + 1)  # sparse: no disk, and never read
    assert _refusal(folder) == ("capture.json: 67108865 bytes, more than the 67108864 a "
                                "capture's description may take")
