"""Checking one frame-set of a stream in memory before it is stored (docs/api.md, Streams).

A frame-set that is stored counts for good (its index is acknowledged, the client deletes it),
and a bad one would only surface when the whole stream is assembled and read; so the gateway
refuses here, naming the entry, whatever it can tell without decoding pixels: the entries'
names, the depth PNGs' headers (16-bit greyscale, the camera's size), the colour images' kind,
and every entry's bytes against its CRC. The gateway never imports the capture reader
(``pipeline``), so these few header reads are its own.
"""

from __future__ import annotations

import io
import struct
import zipfile
import zlib
from collections.abc import Mapping

from isal import isal_zlib

from app.core.problems import ProblemError

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
JPEG_SOI = b"\xff\xd8"
# signature, chunk length, b"IHDR", width, height, bit depth, colour type, 3 more bytes, CRC
_IHDR = struct.Struct(">8sI4sIIBB3sI")
_READ_BYTES = 1024 * 1024
_METHODS = frozenset({zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED})
_LOCAL = struct.Struct("<4s5H3I2H")
"""A local file header: signature, version, flags, method, time, date, CRC, sizes, name and
extra field lengths."""
_LOCAL_SIGNATURE = b"PK\x03\x04"
_UTF8_FLAG = 0x800


def _bad(detail: str) -> ProblemError:
    return ProblemError(422, detail, kind="invalid-frame-set")


def depth_name(camera_id: str, index: int) -> str:
    return f"{camera_id}/depth/{index:06d}.png"


def color_names(camera_id: str, index: int) -> tuple[str, str]:
    return f"{camera_id}/color/{index:06d}.jpg", f"{camera_id}/color/{index:06d}.png"


class _Archive(zipfile.ZipFile):
    """A zip read from the body in memory, with the body at hand to read entries in place."""

    body: memoryview


def _open(data: bytes) -> _Archive:
    try:
        archive = _Archive(io.BytesIO(data))
        archive.body = memoryview(data)  # BytesIO.getbuffer would copy bytes it shares
        return archive
    except (zipfile.BadZipFile, OSError, EOFError, ValueError, NotImplementedError) as exc:
        raise _bad(f"The body is not a readable zip archive ({exc}); a frame-set is a zip of "
                   "<camera>/depth/<index>.png entries.") from None


def _check_entries(infos: list[zipfile.ZipInfo], allowed: set[str],
                   max_unpacked_bytes: int) -> None:
    names = [info.filename for info in infos]
    if len(set(names)) != len(names):
        raise _bad("The frame-set holds two entries of the same name.")
    unpacked_bytes = 0
    for info in infos:
        if info.filename not in allowed:
            raise _bad(f"Unexpected entry {info.filename!r}: a frame-set holds "
                       "<camera>/depth/<index>.png for every camera of the stream, optional "
                       "<camera>/color/<index>.jpg (or .png), nothing else (a live preview goes "
                       "to PUT /streams/{id}/preview).")
        if info.flag_bits & 0x1 or info.compress_type not in _METHODS:
            raise _bad(f"Entry {info.filename!r} is encrypted or compressed with method "
                       f"{info.compress_type}; use stored or deflate, unencrypted.")
        unpacked_bytes += info.file_size
    if unpacked_bytes > max_unpacked_bytes:
        raise ProblemError(413, f"The frame-set unpacks to {unpacked_bytes} bytes, more than "
                           f"{max_unpacked_bytes}.", kind="frame-set-too-large")


def _read_checked(archive: _Archive, name: str, keep_bytes: int) -> bytes:
    """The entry's first ``keep_bytes``, after checking all its bytes against its CRC."""
    info = archive.getinfo(name)
    if info.compress_type == zipfile.ZIP_STORED:
        return _stored_head(archive, info, keep_bytes)
    kept = b""
    try:
        with archive.open(name) as entry:
            while chunk := entry.read(_READ_BYTES):
                if len(kept) < keep_bytes:
                    kept += chunk[:keep_bytes - len(kept)]
    except (zipfile.BadZipFile, zlib.error, OSError, EOFError) as exc:
        raise _bad(f"Entry {name!r} is damaged ({exc}).") from None
    return kept


def _stored_head(archive: _Archive, info: zipfile.ZipInfo, keep_bytes: int) -> bytes:
    """A stored entry's first ``keep_bytes``, its bytes checked in place in the body against
    its CRC with ISA-L.

    zipfile would copy the entry out in pieces and checksum with zlib (2.2 ms for a frame-set
    of 4.4 MB against 0.7 ms). Its checks are kept: the local header where the directory says,
    naming the same entry, and the bytes whole and matching the CRC (the frame-set is
    acknowledged once stored: a damaged one must be refused now, while the client has it)."""
    body = archive.body
    start = info.header_offset
    header = bytes(body[start:start + _LOCAL.size])
    if len(header) < _LOCAL.size or header[:4] != _LOCAL_SIGNATURE:
        raise _bad(f"Entry {info.filename!r} is damaged (no local header where the zip's "
                   "directory says).")
    name_bytes, extra_bytes = _LOCAL.unpack(header)[-2:]
    name_start = start + _LOCAL.size
    encoding = "utf-8" if info.flag_bits & _UTF8_FLAG else "cp437"
    if bytes(body[name_start:name_start + name_bytes]) != info.orig_filename.encode(encoding):
        raise _bad(f"Entry {info.filename!r} is damaged (its local header names another).")
    begin = name_start + name_bytes + extra_bytes
    end = begin + info.compress_size
    if end > len(body) or info.compress_size != info.file_size:
        raise _bad(f"Entry {info.filename!r} is damaged (truncated).")
    if isal_zlib.crc32(body[begin:end]) != info.CRC:
        raise _bad(f"Entry {info.filename!r} is damaged (its bytes do not match its CRC).")
    return bytes(body[begin:min(end, begin + keep_bytes)])


def _check_depth(archive: _Archive, name: str, size: tuple[int, int]) -> None:
    head = _read_checked(archive, name, _IHDR.size)
    if len(head) < _IHDR.size or not head.startswith(PNG_SIGNATURE):
        raise _bad(f"Entry {name!r} is not a PNG image.")
    _, length, chunk, width, height, bit_depth, colour_type, _, crc = _IHDR.unpack(head)
    if chunk != b"IHDR" or length != 13:
        raise _bad(f"Entry {name!r} is not a PNG image (no IHDR chunk first).")
    if zlib.crc32(head[12:29]) != crc:
        raise _bad(f"Entry {name!r} is damaged (its PNG header's checksum does not match).")
    if (bit_depth, colour_type) != (16, 0):
        raise _bad(f"Entry {name!r} is a PNG of bit depth {bit_depth} and colour type "
                   f"{colour_type}; depth is a 16-bit greyscale PNG (bit depth 16, colour "
                   "type 0).")
    if (width, height) != size:
        raise _bad(f"Entry {name!r} is {width}x{height} pixels; the camera's depth_intrinsics "
                   f"say {size[0]}x{size[1]}.")


def _check_color(archive: _Archive, name: str) -> None:
    head = _read_checked(archive, name, len(PNG_SIGNATURE))
    magic = JPEG_SOI if name.endswith(".jpg") else PNG_SIGNATURE
    if not head.startswith(magic):
        kind = "JPEG" if magic == JPEG_SOI else "PNG"
        raise _bad(f"Entry {name!r} is not a {kind} image.")


def check_frame_set(data: bytes, index: int, depth_sizes: Mapping[str, tuple[int, int]],
                    max_unpacked_bytes: int) -> None:
    """Refuse a frame-set that is not exactly what the stream expects for ``index``:
    ``depth_sizes`` maps each camera id to its depth (width, height). ``ProblemError`` 422
    (413 when it unpacks to over ``max_unpacked_bytes``) names the entry at fault."""
    with _open(data) as archive:
        infos = archive.infolist()
        allowed: set[str] = set()
        for camera_id in depth_sizes:
            allowed.update((depth_name(camera_id, index), *color_names(camera_id, index)))
        _check_entries(infos, allowed, max_unpacked_bytes)
        present = {info.filename: info for info in infos}
        for camera_id, size in depth_sizes.items():
            name = depth_name(camera_id, index)
            if name not in present:
                raise _bad(f"Entry {name!r} is missing: every camera of the stream needs its "
                           "depth in every frame-set.")
            _check_depth(archive, name, size)
            colors = [n for n in color_names(camera_id, index) if n in present]
            if len(colors) > 1:
                raise _bad(f"Entries {colors[0]!r} and {colors[1]!r}: one colour image per "
                           "camera.")
            for color in colors:
                _check_color(archive, color)
