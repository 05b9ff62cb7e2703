"""A capture's images checked from their headers (size against the intrinsics, a pixel cap,
the file's length) before any pixel is decoded, then decoded; so neither a hostile image nor
a damaged one can exhaust or crash a reader. Errors are ``ValueError`` naming the file."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import cast

import cv2
import numpy as np
from numpy.typing import NDArray

from pipeline.capture import CaptureMeta, Intrinsics
from pipeline.io.image_header import (
    Bytes,
    ImageHeader,
    TruncatedHeaderError,
    png_header,
    read_image_header,
)

# Header reads grow until the size is found: a PNG's is in its first 33 bytes, a JPEG's may
# follow EXIF, XMP and ICC segments of up to 64 KiB each.
_HEAD_READS_BYTES = (64, 64 * 1024, 1024 * 1024)
# An image file may hold this much beyond twice its decoded pixels (metadata, poor
# compression); a longer one is refused before it is read into memory.
_SLACK_BYTES = 1024 * 1024


@dataclass(frozen=True)
class ImageSpec:
    """What one image file of a capture must be."""

    path: str
    intrinsics: Intrinsics
    intrinsics_name: str
    """The capture.json field the size comes from, for messages."""
    max_pixels: int
    depth: bool
    """A depth image: a 16-bit single-channel PNG; otherwise colour, JPEG or PNG."""

    def parse(self, head: Bytes) -> ImageHeader:
        return png_header(head) if self.depth else read_image_header(head)


def check_declared_sizes(meta: CaptureMeta, max_pixels: int) -> None:
    """Refuses intrinsics whose image size is over the pixel cap, naming the field."""
    for i, camera in enumerate(meta.cameras):
        for name, intr in (("depth_intrinsics", camera.depth_intrinsics),
                           ("color_intrinsics", camera.color_intrinsics)):
            if intr is not None and intr.width * intr.height > max_pixels:
                raise ValueError(f"capture.json: cameras[{i}].{name}: {intr.width}x"
                                 f"{intr.height} is {intr.width * intr.height} pixels, over "
                                 f"the limit of {max_pixels} pixels per image")


def check_image_file(read_head: Callable[[int], Bytes], size_bytes: int,
                     spec: ImageSpec) -> None:
    """Checks a stored image from its header and length, reading only its first bytes."""
    header = _header_of_file(read_head, spec)
    check_header(header, spec)
    most_bytes = 2 * header.decoded_bytes + _SLACK_BYTES
    if size_bytes > most_bytes:
        raise ValueError(f"{spec.path}: the file has {size_bytes} bytes, more than a "
                         f"{header.width}x{header.height} image can need ({most_bytes})")


def _header_of_file(read_head: Callable[[int], Bytes], spec: ImageSpec) -> ImageHeader:
    for size in _HEAD_READS_BYTES:
        head = read_head(size)
        try:
            return spec.parse(head)
        except TruncatedHeaderError as exc:
            if len(head) < size or size == _HEAD_READS_BYTES[-1]:
                raise ValueError(f"{spec.path}: {exc}") from None
        except ValueError as exc:
            raise ValueError(f"{spec.path}: {exc}") from None
    raise AssertionError("unreachable: the last read returns or raises")


def check_header(header: ImageHeader, spec: ImageSpec) -> None:
    """Refuses an image over the pixel cap, of the wrong kind, or not of its declared size."""
    if header.pixels > spec.max_pixels:
        raise ValueError(f"{spec.path}: image is {header.width}x{header.height}, "
                         f"{header.pixels} pixels, over the limit of {spec.max_pixels} pixels")
    if spec.depth and (header.bit_depth != 16 or header.png_color_type != 0):
        raise ValueError(f"{spec.path}: depth must be a 16-bit single-channel PNG, got bit "
                         f"depth {header.bit_depth}, PNG colour type {header.png_color_type}")
    intr = spec.intrinsics
    if (header.width, header.height) != (intr.width, intr.height):
        raise ValueError(f"{spec.path}: image is {header.width}x{header.height} but "
                         f"{spec.intrinsics_name} say {intr.width}x{intr.height}")


def decode_depth(data: Bytes, spec: ImageSpec) -> NDArray[np.uint16]:
    """A depth image's raw 16-bit values, its header checked first."""
    raw = _decode(data, cv2.IMREAD_UNCHANGED, spec)
    if raw.dtype != np.uint16 or raw.ndim != 2:
        raise ValueError(f"{spec.path}: depth must be a 16-bit single-channel PNG")
    return cast(NDArray[np.uint16], raw)


def decode_color_rgb(data: Bytes, spec: ImageSpec) -> NDArray[np.uint8]:
    """A colour image as 8-bit RGB, its header checked first."""
    image = cast(NDArray[np.uint8], _decode(data, cv2.IMREAD_COLOR, spec))
    cv2.cvtColor(image, cv2.COLOR_BGR2RGB, dst=image)  # in place: no second copy of the image
    return image


def _decode(data: Bytes, flags: int, spec: ImageSpec) -> NDArray[np.generic]:
    try:
        header = spec.parse(data)
    except ValueError as exc:
        raise ValueError(f"{spec.path}: {exc}") from None
    check_header(header, spec)
    try:
        image = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    except cv2.error as exc:  # OpenCV refuses some damaged streams by raising
        raise ValueError(f"{spec.path}: image data are corrupt ({exc.err})") from None
    if image is None:
        raise ValueError(f"{spec.path}: image data are corrupt")
    return image
