"""An image's size from its first bytes (the PNG IHDR chunk or the JPEG start-of-frame), so a
capture's images are checked against their intrinsics and a pixel cap before any is decoded.

Pure functions on bytes: errors are ``ValueError`` with no file name (the caller adds it), and
``TruncatedHeaderError`` when the bytes end before the size, so a caller may read more.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass

Bytes = bytes | bytearray
"""A file's bytes as the capture reader holds them (a whole zip entry is read into a bytearray)."""
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
JPEG_SIGNATURE = b"\xff\xd8"
_PNG_HEADER_BYTES = 33  # signature, IHDR length and type, 13 bytes of IHDR, its CRC
_PNG_MAX_SIDE = 2**31 - 1  # the PNG specification's bound on width and height
_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}  # PNG colour type -> samples per pixel
# Start-of-frame markers: every C0-CF except DHT (C4), JPG (C8) and DAC (CC).
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
_JPEG_STANDALONE = frozenset({0x01, *range(0xD0, 0xD8)})  # TEM, RST0-7: no length field
_JPEG_IMAGE_DATA = frozenset({0xD9, 0xDA})  # EOI, SOS: past where a frame header must be


class TruncatedHeaderError(ValueError):
    """The bytes end before the image's size: the file is cut short, or more must be read."""


@dataclass(frozen=True)
class ImageHeader:
    """What an image's header says about its pixels."""

    kind: str
    """'png' or 'jpeg'."""
    width: int
    height: int
    bit_depth: int
    """Bits per sample: PNG bit depth, JPEG sample precision."""
    channels: int
    """Samples per pixel (a PNG palette image counts one)."""
    png_color_type: int | None = None
    """PNG colour type (0 greyscale, 2 RGB, 3 palette, 4 grey+alpha, 6 RGBA); None for JPEG."""

    @property
    def pixels(self) -> int:
        return self.width * self.height

    @property
    def decoded_bytes(self) -> int:
        """Bytes the decoded pixels take at the header's bit depth (rounded up to bytes)."""
        return self.pixels * self.channels * max(1, (self.bit_depth + 7) // 8)


def read_image_header(head: Bytes) -> ImageHeader:
    """The header of a PNG or JPEG image from its first bytes."""
    if head.startswith(PNG_SIGNATURE):
        return png_header(head)
    if head.startswith(JPEG_SIGNATURE):
        return jpeg_header(head)
    if len(head) < len(PNG_SIGNATURE) and (PNG_SIGNATURE.startswith(head)
                                           or JPEG_SIGNATURE.startswith(head)):
        raise TruncatedHeaderError(f"image ends after {len(head)} bytes, before its header")
    raise ValueError("not a JPEG or PNG image")


def png_header(head: Bytes) -> ImageHeader:
    """The IHDR chunk of a PNG, which the specification puts first."""
    if not head.startswith(PNG_SIGNATURE):
        raise ValueError("not a PNG image")
    if len(head) < _PNG_HEADER_BYTES:
        raise TruncatedHeaderError(f"PNG ends after {len(head)} bytes, inside its header")
    length, chunk_type = struct.unpack(">I4s", head[8:16])
    if chunk_type != b"IHDR" or length != 13:
        raise ValueError("PNG does not start with an IHDR chunk")
    (crc,) = struct.unpack(">I", head[29:33])
    if zlib.crc32(head[12:29]) != crc:
        raise ValueError("PNG header is corrupt (IHDR checksum mismatch)")
    width, height, bit_depth, color_type = struct.unpack(">IIBB", head[16:26])
    if not (1 <= width <= _PNG_MAX_SIDE and 1 <= height <= _PNG_MAX_SIDE):
        raise ValueError(f"PNG header gives an impossible size {width}x{height}")
    if color_type not in _PNG_CHANNELS:
        raise ValueError(f"PNG header gives an unknown colour type {color_type}")
    return ImageHeader("png", width, height, bit_depth, _PNG_CHANNELS[color_type], color_type)


def jpeg_header(head: Bytes) -> ImageHeader:
    """The start-of-frame segment of a JPEG, found by walking the segments before it."""
    if not head.startswith(JPEG_SIGNATURE):
        raise ValueError("not a JPEG image")
    at = 2
    while True:
        at = _next_marker(head, at)
        marker = head[at + 1]
        if marker in _JPEG_STANDALONE:
            at += 2
            continue
        if marker in (0x00, 0xD8):  # a stuffed byte or a second start: not a segment
            raise ValueError(f"JPEG is corrupt: no segment marker at byte {at}")
        if marker in _JPEG_IMAGE_DATA:
            raise ValueError("JPEG has no frame header before its image data")
        if at + 4 > len(head):
            raise _jpeg_truncated(head)
        (length,) = struct.unpack(">H", head[at + 2:at + 4])
        if length < 2:
            raise ValueError(f"JPEG segment at byte {at} has an impossible length {length}")
        if marker in _JPEG_SOF:
            return _jpeg_frame(head, at, length)
        at += 2 + length


def _next_marker(head: Bytes, at: int) -> int:
    """Index of the next marker's 0xFF at or after ``at``, skipping fill bytes."""
    if at >= len(head):
        raise _jpeg_truncated(head)
    if head[at] != 0xFF:
        raise ValueError(f"JPEG is corrupt: no segment marker at byte {at}")
    while at + 1 < len(head) and head[at + 1] == 0xFF:
        at += 1  # 0xFF fill bytes may pad the space between segments
    if at + 1 >= len(head):
        raise _jpeg_truncated(head)
    return at


def _jpeg_frame(head: Bytes, at: int, length: int) -> ImageHeader:
    if length < 8:
        raise ValueError(f"JPEG frame header has an impossible length {length}")
    if at + 10 > len(head):
        raise _jpeg_truncated(head)
    precision, height, width, components = struct.unpack(">BHHB", head[at + 4:at + 10])
    if width == 0 or height == 0:
        raise ValueError(f"JPEG frame header gives no size ({width}x{height})")
    if components == 0:
        raise ValueError("JPEG frame header has no colour components")
    return ImageHeader("jpeg", width, height, precision, components)


def _jpeg_truncated(head: Bytes) -> TruncatedHeaderError:
    return TruncatedHeaderError(f"JPEG ends after {len(head)} bytes, before its frame header")
