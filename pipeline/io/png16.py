"""16-bit greyscale PNG encoding fast enough for depth video on a small CPU.

OpenCV's PNG writer (zlib) takes ~15–25 ms for a noisy 640×576 depth image; eight cameras at
30 fps on two cores leave ~6 ms per image for everything. This writes the same standard PNG
(signature, IHDR with bit depth 16 and colour type 0, one IDAT, IEND) with the rows deflated
by ISA-L at level 1 (~3 ms, files as small as zlib level 1). ISA-L's deflate releases the GIL,
so images encode side by side in threads. CRCs are ISA-L's CRC-32 (the same as zlib.crc32, four
times faster).
"""

from __future__ import annotations

import struct
import threading

import numpy as np
from isal import isal_zlib
from numpy.typing import NDArray

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
DEFLATE_LEVEL = 1
"""ISA-L's level 1: levels 0–3 cost about the same here, and 1 is within 2 % of 3's size."""
_UP = 2
"""PNG filter type Up: each byte less the byte above it. On real Kinect depth it makes files
~11 % smaller than no filter (smooth surfaces repeat row to row) for ~0.5 ms an image."""
_MAX_SIDE_PX = 2**31 - 1  # PNG's limit on width and height


def _chunk(kind: bytes, data: bytes) -> tuple[bytes, bytes, bytes]:
    """A PNG chunk in three parts (length and type, data, CRC-32 of type and data), so that
    a large IDAT is copied once, when the file is joined."""
    crc = isal_zlib.crc32(data, isal_zlib.crc32(kind))
    return struct.pack(">I", len(data)) + kind, data, struct.pack(">I", crc)


def _header(height_px: int, width_px: int) -> bytes:
    """IHDR: 16-bit greyscale, deflate, adaptive filtering, no interlace."""
    return b"".join(_chunk(b"IHDR", struct.pack(">IIBBBBB", width_px, height_px, 16, 0, 0, 0,
                                                 0)))


_IEND = b"".join(_chunk(b"IEND", b""))
_per_thread = threading.local()


def up_filtered_rows(image: NDArray[np.uint16],
                     out: NDArray[np.uint8] | None = None) -> NDArray[np.uint8]:
    """(H, 1 + 2W) bytes: each row of (H, W) samples as big-endian bytes (PNG's order) after
    its filter-type byte, Up-filtered (the first row's 'above' is zeros, so it stays raw).
    Written into ``out`` where given (of that shape)."""
    height, width = image.shape
    raw = np.ascontiguousarray(image, dtype=">u2").view(np.uint8).reshape(height, 2 * width)
    rows = np.empty((height, 1 + 2 * width), np.uint8) if out is None else out
    rows[:, 0] = _UP
    rows[0, 1:] = raw[0]
    np.subtract(raw[1:], raw[:-1], out=rows[1:, 1:])  # uint8 wraps modulo 256, as PNG's does
    return rows


def _rows_buffer(height: int, width: int) -> NDArray[np.uint8]:
    """This thread's buffer for the filtered rows of an image of this size, kept across
    images: a fresh ~0.7 MB array per image goes back to the system when freed (glibc trims
    a thread's heap once that much at its top is free) and is faulted in again page by page,
    which cost more than the filtering (an import of eight recordings: 0.7 M page faults,
    not 40 k). Holds the last size's buffer while the thread lives."""
    shape = (height, 1 + 2 * width)
    buffer: NDArray[np.uint8] | None = getattr(_per_thread, "rows", None)
    if buffer is None or buffer.shape != shape:
        buffer = _per_thread.rows = np.empty(shape, np.uint8)
    return buffer


def encode_png16(image: NDArray[np.uint16]) -> bytes:
    """A (H, W) uint16 image as a 16-bit greyscale PNG file's bytes. Big-endian samples
    (``>u2``, as a Kinect recording holds them) are taken without a byte swap.

    ValueError for anything else (another dtype or rank, an empty or oversized image)."""
    return b"".join(png16_parts(image))


def png16_parts(image: NDArray[np.uint16]) -> tuple[bytes, ...]:
    """The bytes of :func:`encode_png16`'s file in pieces, to be written in order: a writer
    that gathers them (``os.writev``) spares the copy of the compressed rows a join makes."""
    if image.ndim != 2 or image.dtype.kind != "u" or image.dtype.itemsize != 2:
        raise ValueError(f"a 16-bit PNG takes a (H, W) uint16 image, got {image.dtype} "
                         f"{image.shape}")
    height, width = image.shape
    if not (0 < height <= _MAX_SIDE_PX and 0 < width <= _MAX_SIDE_PX):
        raise ValueError(f"a PNG is 1 to {_MAX_SIDE_PX} pixels a side, got {width}x{height}")
    rows = up_filtered_rows(image, _rows_buffer(height, width))
    compressed = isal_zlib.compress(rows, DEFLATE_LEVEL)
    idat_head, idat, idat_crc = _chunk(b"IDAT", compressed)
    return PNG_SIGNATURE + _header(height, width) + idat_head, idat, idat_crc + _IEND
