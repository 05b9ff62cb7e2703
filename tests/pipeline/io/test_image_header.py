"""Image sizes from header bytes: real PNGs and JPEGs read right, every cut-short header says
so, and no byte string makes the reader fail other than with a ValueError."""

from __future__ import annotations

import re
import struct

import cv2
import numpy as np
import pytest
from hypothesis import example, given
from hypothesis import strategies as st

from pipeline.io.image_header import (
    ImageHeader,
    TruncatedHeaderError,
    jpeg_header,
    png_header,
    read_image_header,
)
from tests.hostile_captures import png_bomb, png_chunk, png_ihdr


def _encoded(suffix: str, image: np.ndarray, *params: int) -> bytes:
    ok, buffer = cv2.imencode(suffix, image, list(params))
    assert ok
    return buffer.tobytes()


def _jpeg_with_app_segment(payload_bytes: int) -> bytes:
    """A real JPEG with an APP1 segment of ``payload_bytes`` before its frame header."""
    jpeg = _encoded(".jpg", np.zeros((7, 9, 3), np.uint8))
    return jpeg[:2] + b"\xff\xe1" + struct.pack(">H", payload_bytes + 2) + bytes(
        payload_bytes) + jpeg[2:]


SIXTEEN_BIT = np.zeros((12, 16), np.uint16)
REAL_IMAGES = {
    "16-bit grey PNG": (_encoded(".png", SIXTEEN_BIT), ImageHeader("png", 16, 12, 16, 1, 0)),
    "8-bit RGB PNG": (_encoded(".png", np.zeros((5, 3, 3), np.uint8)),
                      ImageHeader("png", 3, 5, 8, 3, 2)),
    "RGBA PNG": (_encoded(".png", np.zeros((2, 7, 4), np.uint8)),
                 ImageHeader("png", 7, 2, 8, 4, 6)),
    "colour JPEG": (_encoded(".jpg", np.zeros((48, 64, 3), np.uint8)),
                    ImageHeader("jpeg", 64, 48, 8, 3)),
    "grey progressive JPEG": (_encoded(".jpg", np.zeros((33, 17), np.uint8),
                                       cv2.IMWRITE_JPEG_PROGRESSIVE, 1),
                              ImageHeader("jpeg", 17, 33, 8, 1)),
    "JPEG with a 60 KiB APP1": (_jpeg_with_app_segment(60_000), ImageHeader("jpeg", 9, 7, 8, 3)),
    "PNG bomb": (png_ihdr(12000, 12000), ImageHeader("png", 12000, 12000, 16, 1, 0)),
}


@pytest.mark.parametrize("name", sorted(REAL_IMAGES))
def test_real_images_give_their_size(name: str) -> None:
    data, expected = REAL_IMAGES[name]
    assert read_image_header(data) == expected


def test_the_png_bomb_is_small_and_says_what_it_decodes_to() -> None:
    bomb = png_bomb(2000, 1000)
    header = read_image_header(bomb)
    assert (header.width, header.height, header.decoded_bytes) == (2000, 1000, 4_000_000)
    assert len(bomb) < 10_000


@pytest.mark.parametrize("name", sorted(REAL_IMAGES))
def test_every_cut_short_header_says_it_is_truncated(name: str) -> None:
    data, _ = REAL_IMAGES[name]
    needed = next(n for n in range(1, len(data) + 1) if _reads(data[:n]))
    for n in range(needed):
        with pytest.raises(TruncatedHeaderError):
            read_image_header(data[:n])


def _reads(head: bytes) -> bool:
    try:
        read_image_header(head)
    except TruncatedHeaderError:
        return False
    return True


def _sof(width: int, height: int) -> bytes:
    return b"\xff\xc0" + struct.pack(">HBHHB", 11, 8, height, width, 1) + b"\x01\x11\x00"


BROKEN = {
    "empty": (b"", "before its header"),
    "GIF": (b"GIF89a" + bytes(40), "not a JPEG or PNG"),
    "PNG without IHDR first": (b"\x89PNG\r\n\x1a\n" + png_chunk(b"tEXt", bytes(13)),
                               "does not start with an IHDR"),
    "PNG IHDR checksum": (png_ihdr(4, 4)[:-1] + b"\x00", "checksum mismatch"),
    "PNG width zero": (png_ihdr(0, 4), "impossible size 0x4"),
    "PNG width over 2^31": (png_ihdr(2**31, 4), "impossible size"),
    "PNG unknown colour type": (png_ihdr(4, 4, 8, 5), "unknown colour type 5"),
    "JPEG SOS before SOF": (b"\xff\xd8\xff\xda\x00\x02", "no frame header before"),
    "JPEG end before SOF": (b"\xff\xd8\xff\xd9", "no frame header before"),
    "JPEG garbage between segments": (b"\xff\xd8\x00\x00\x00\x00", "no segment marker"),
    "JPEG segment length 1": (b"\xff\xd8\xff\xe0\x00\x01\x00\x00", "impossible length 1"),
    "JPEG frame of zero height": (b"\xff\xd8" + _sof(8, 0), "gives no size (8x0)"),
    "JPEG frame too short": (b"\xff\xd8\xff\xc0\x00\x04\x08\x00", "impossible length 4"),
}


@pytest.mark.parametrize("name", sorted(BROKEN))
def test_broken_headers_are_refused_saying_why(name: str) -> None:
    data, expected = BROKEN[name]
    with pytest.raises(ValueError, match=re.escape(expected)):
        read_image_header(data)


def test_fill_bytes_and_restart_markers_before_the_frame_are_skipped() -> None:
    head = b"\xff\xd8\xff\xff\xff\xd0" + _sof(640, 576)
    assert read_image_header(head) == ImageHeader("jpeg", 640, 576, 8, 1)


def test_each_reader_refuses_the_other_kind() -> None:
    with pytest.raises(ValueError, match="not a PNG"):
        png_header(REAL_IMAGES["colour JPEG"][0])
    with pytest.raises(ValueError, match="not a JPEG"):
        jpeg_header(REAL_IMAGES["8-bit RGB PNG"][0])


@given(width=st.integers(1, 2**31 - 1), height=st.integers(1, 2**31 - 1),
       depth=st.sampled_from([1, 2, 4, 8, 16]), color_type=st.sampled_from([0, 2, 3, 4, 6]))
def test_any_png_size_is_read_back(width: int, height: int, depth: int, color_type: int) -> None:
    header = png_header(png_ihdr(width, height, depth, color_type) + b"rest of the file")
    assert (header.width, header.height, header.bit_depth) == (width, height, depth)
    assert header.pixels == width * height


@given(width=st.integers(1, 65535), height=st.integers(1, 65535),
       app_bytes=st.lists(st.integers(0, 300), max_size=4))
def test_any_jpeg_size_is_read_back_after_any_segments(width: int, height: int,
                                                         app_bytes: list[int]) -> None:
    segments = b"".join(b"\xff\xe0" + struct.pack(">H", n + 2) + bytes(n) for n in app_bytes)
    header = jpeg_header(b"\xff\xd8" + segments + _sof(width, height))
    assert (header.width, header.height) == (width, height)


@given(st.binary(max_size=200))
@example(b"\xff\xd8\xff")
@example(b"\x89PNG\r\n\x1a\n")
def test_no_bytes_crash_the_reader(data: bytes) -> None:
    for head in (data, b"\xff\xd8" + data, b"\x89PNG\r\n\x1a\n" + data):
        try:
            header = read_image_header(head)
        except ValueError:
            continue
        assert header.width >= 1 and header.height >= 1
