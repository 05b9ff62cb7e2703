"""The 16-bit greyscale PNG encoder: bit-exact through two decoders, and a well-formed file."""

from __future__ import annotations

import io
import struct
import zlib

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from numpy.typing import NDArray
from PIL import Image

from pipeline.io.png16 import PNG_SIGNATURE, encode_png16

_SAMPLES = st.one_of(st.sampled_from([0, 1, 255, 256, 65534, 65535]), st.integers(0, 65535))


def _images() -> st.SearchStrategy[NDArray[np.uint16]]:
    shapes = st.tuples(st.integers(1, 40), st.integers(1, 40))
    return arrays(st.sampled_from([np.dtype("<u2"), np.dtype(">u2")]), shapes,
                  elements=_SAMPLES)


def _chunks(png: bytes) -> list[tuple[bytes, bytes]]:
    """(type, data) of every chunk, each CRC and length checked: a strict reader."""
    assert png[:8] == PNG_SIGNATURE
    chunks, at = [], 8
    while at < len(png):
        (length,) = struct.unpack(">I", png[at:at + 4])
        kind, data = png[at + 4:at + 8], png[at + 8:at + 8 + length]
        assert len(data) == length, f"{kind!r}: shorter than its length"
        (crc,) = struct.unpack(">I", png[at + 8 + length:at + 12 + length])
        assert crc == zlib.crc32(kind + data), f"{kind!r}: CRC mismatch"
        chunks.append((kind, data))
        at += 12 + length
    assert at == len(png)
    return chunks


def _unfilter(rows: bytes, height: int, width: int) -> NDArray[np.uint16]:
    """PNG's filters 0 (None) and 2 (Up) undone, done independently of the encoder."""
    stride = 1 + 2 * width
    out = np.zeros((height, 2 * width), np.uint8)
    for y in range(height):
        kind, line = rows[y * stride], np.frombuffer(rows, np.uint8, 2 * width, y * stride + 1)
        assert kind in (0, 2), f"row {y}: filter type {kind}"
        above = out[y - 1] if y > 0 and kind == 2 else np.zeros(2 * width, np.uint8)
        out[y] = line + above  # uint8 wraps modulo 256, as PNG's sums do
    return out.view(">u2").astype(np.uint16)


@settings(max_examples=150, deadline=None)
@given(image=_images())
def test_any_image_reads_back_bit_exactly_through_opencv_and_pillow(
        image: NDArray[np.uint16]) -> None:
    png = encode_png16(image)
    by_cv2 = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
    assert by_cv2.dtype == np.uint16 and by_cv2.shape == image.shape
    np.testing.assert_array_equal(by_cv2, image)
    with Image.open(io.BytesIO(png)) as picture:
        assert picture.mode == "I;16" and picture.size == image.shape[::-1]
        by_pil = np.asarray(picture)
    np.testing.assert_array_equal(by_pil.astype(np.int64), image.astype(np.int64))


@settings(max_examples=60, deadline=None)
@given(image=_images())
def test_the_file_is_well_formed_by_a_strict_reading(image: NDArray[np.uint16]) -> None:
    png = encode_png16(image)
    chunks = _chunks(png)
    assert [kind for kind, _ in chunks] == [b"IHDR", b"IDAT", b"IEND"]
    height, width = image.shape
    assert chunks[0][1] == struct.pack(">IIBBBBB", width, height, 16, 0, 0, 0, 0)
    assert chunks[2][1] == b""
    rows = zlib.decompress(chunks[1][1])  # a zlib stream with its Adler-32, as PNG requires
    assert len(rows) == height * (1 + 2 * width)
    np.testing.assert_array_equal(_unfilter(rows, height, width), image)
    with Image.open(io.BytesIO(png)) as picture:
        picture.verify()  # Pillow's own CRC check of every chunk


def test_a_damaged_crc_is_caught_by_the_strict_readings() -> None:
    """The checks above can fail: one flipped bit in the IDAT's data is refused by both."""
    image = np.arange(12 * 10, dtype=np.uint16).reshape(12, 10) * 500
    png = bytearray(encode_png16(image))
    png[8 + 25 + 8 + 3] ^= 0x01  # a byte of the IDAT's data (after signature and IHDR)
    with pytest.raises(AssertionError, match="CRC"):
        _chunks(bytes(png))
    with pytest.raises(SyntaxError), Image.open(io.BytesIO(bytes(png))) as picture:
        picture.verify()


def test_a_depth_sized_image_matches_opencv_decoding_and_compresses_like_it() -> None:
    rng = np.random.default_rng(0)
    depth = np.where(rng.random((576, 640)) < 0.05, 0,
                     rng.normal(2000, 2, (576, 640))).round().astype(np.uint16)
    png = encode_png16(depth)
    np.testing.assert_array_equal(cv2.imdecode(np.frombuffer(png, np.uint8), -1), depth)
    opencv = cv2.imencode(".png", depth, [cv2.IMWRITE_PNG_COMPRESSION, 1])[1]
    assert len(png) < 1.1 * len(opencv)


@pytest.mark.parametrize("image", [
    np.zeros((4, 4), np.uint8), np.zeros((4, 4), np.int16), np.zeros((4, 4, 1), np.uint16),
    np.zeros((0, 4), np.uint16), np.zeros((4, 0), np.uint16)])
def test_anything_but_a_nonempty_uint16_image_is_refused(image: NDArray[np.generic]) -> None:
    with pytest.raises(ValueError, match="16-bit PNG|pixels a side"):
        encode_png16(image)  # type: ignore[arg-type]
