"""Hostile captures for the tests and the validation benchmark: a zip whose directory is valid
but whose member data are damaged, and a PNG bomb (a small file that decodes to gigabytes)."""

from __future__ import annotations

import io
import json
import struct
import zipfile
import zlib

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
BOMB_SIDE_PX = 12000
BOMB_MEMBER = "cam0/depth/000000.png"


def png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def png_ihdr(width: int, height: int, bit_depth: int = 16, color_type: int = 0) -> bytes:
    """A PNG's signature and IHDR chunk: the first 33 bytes of a valid PNG."""
    fields = struct.pack(">IIBBBBB", width, height, bit_depth, color_type, 0, 0, 0)
    return PNG_SIGNATURE + png_chunk(b"IHDR", fields)


def padded_png(png: bytes, extra_bytes: int) -> bytes:
    """``png`` with a private ancillary chunk (decoders skip it) of ``extra_bytes`` after its
    header: still a valid image, but a file long enough that reading its header does not
    reach damage placed in its middle."""
    return png[:33] + png_chunk(b"ppAd", b"x" * extra_bytes) + png[33:]


def png_bomb(width: int = BOMB_SIDE_PX, height: int = BOMB_SIDE_PX) -> bytes:
    """A valid 16-bit greyscale PNG of zeros, compressed on the fly (never held decoded):
    12000x12000 is about 280 KB that decode to 288 MB."""
    row = bytes(1 + 2 * width)  # filter byte 0, then the row's zero samples
    packer = zlib.compressobj(9)
    rows_per_block = 64
    parts = [packer.compress(row * rows_per_block) for _ in range(height // rows_per_block)]
    parts += [packer.compress(row * (height % rows_per_block)), packer.flush()]
    return (png_ihdr(width, height) + png_chunk(b"IDAT", b"".join(parts))
            + png_chunk(b"IEND", b""))


def capture_json(width: int, height: int) -> bytes:
    """capture.json of one posed camera at one frame, images ``width`` x ``height``."""
    intrinsics = {"width": width, "height": height, "fx": width / 2, "fy": width / 2,
                  "cx": width / 2, "cy": height / 2}
    pose = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    return json.dumps({"format": "volumesh.capture/1", "depth_scale": 0.001,
                       "cameras": [{"id": "cam0", "depth_intrinsics": intrinsics,
                                    "world_from_depth": pose}],
                       "frames": [{"index": 0}]}).encode()


def bomb_capture_zip(side_px: int = BOMB_SIDE_PX) -> bytes:
    """A capture whose one depth image is a PNG bomb, with intrinsics that match it."""
    return pack({"capture.json": capture_json(side_px, side_px),
                 BOMB_MEMBER: png_bomb(side_px, side_px)})


def pack(entries: dict[str, bytes], method: int = zipfile.ZIP_STORED) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=method) as archive:
        for name, data in entries.items():
            archive.writestr(name, data)
    return buffer.getvalue()


def damaged_member_zip(entries: dict[str, bytes], member: str, how: str = "crc") -> bytes:
    """``entries`` zipped with the data of ``member`` damaged while the zip's directory stays
    valid: ``crc`` flips a stored byte in its middle (a CRC mismatch), ``deflate`` gives its
    deflate stream a reserved block type (zlib fails), ``truncate`` says it is longer than
    the file holds (its data end early)."""
    if how == "truncate":  # the member last, so its claimed length runs past the file's end
        entries = {**{n: d for n, d in entries.items() if n != member}, member: entries[member]}
    method = zipfile.ZIP_DEFLATED if how == "deflate" else zipfile.ZIP_STORED
    data = bytearray(pack(entries, method))
    info = zipfile.ZipFile(io.BytesIO(bytes(data))).getinfo(member)
    start = info.header_offset + 30 + len(info.orig_filename.encode()) + len(info.extra)
    if how == "crc":
        data[start + info.compress_size // 2] ^= 0xFF
    elif how == "deflate":
        data[start] = 0x07  # final block, block type 3: reserved, invalid
    elif how == "truncate":
        record = central_record(data, member)
        claimed = info.file_size + 512 * 1024
        struct.pack_into("<II", data, record + 20, claimed, claimed)
    else:
        raise ValueError(f"unknown damage {how!r}")
    return bytes(data)


def central_record(data: bytes | bytearray, member: str) -> int:
    """Offset of ``member``'s record in the zip's central directory (flags at +8, compression
    method at +10, compressed size at +20, name at +46)."""
    start = zipfile.ZipFile(io.BytesIO(bytes(data))).start_dir  # type: ignore[attr-defined]
    record = bytes(data).index(b"PK\x01\x02", start)
    while data[record + 46:record + 46 + len(member)] != member.encode():
        record = bytes(data).index(b"PK\x01\x02", record + 4)
    return record
