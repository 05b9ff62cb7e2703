"""Where a capture's files live, a directory or a zip, behind one interface whose every read
error is a ``ValueError`` naming the file, so a damaged capture is refused, never crashes.

Paths are POSIX and relative to the capture's root (the folder holding capture.json).
"""

from __future__ import annotations

import contextlib
import lzma
import os
import re
import zipfile
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import IO

from pipeline.io.image_header import Bytes

# What reading a stored file can raise when its bytes are damaged: a zip's CRC or headers
# (BadZipFile), broken deflate/LZMA/bzip2 streams (zlib.error, LZMAError, OSError), data that
# end early (EOFError), an unsupported or encrypted entry (NotImplementedError, RuntimeError).
READ_ERRORS: tuple[type[Exception], ...] = (
    zipfile.BadZipFile, zlib.error, lzma.LZMAError, EOFError, OSError, NotImplementedError,
    RuntimeError)
_CHUNK_BYTES = 1024 * 1024
_OPEN_ERRORS: tuple[type[Exception], ...] = (*READ_ERRORS, ValueError)


@dataclass(frozen=True)
class ArchiveLimits:
    """Limits that keep a hostile capture from exhausting memory or disk."""

    max_files: int = 200_000
    """Most entries a capture zip may hold."""
    max_unpacked_bytes: int = 16 * 1024**3
    """Largest total uncompressed size, bytes."""
    max_compression_ratio: float = 200.0
    """Largest uncompressed/compressed ratio of one entry (zip bombs go far beyond)."""
    max_image_pixels: int = 25_000_000
    """Most pixels of one image, declared or stored (about twice the Azure Kinect's largest
    colour mode, 4096x3072); the service's default (VOLUMESH_MAX_IMAGE_PIXELS) is the same."""


@contextlib.contextmanager
def reading(path: str) -> Iterator[None]:
    """Turns the read error of a damaged (or unreadable) file into a ValueError naming it."""
    try:
        yield
    except EOFError:
        raise ValueError(f"{path}: cannot be read (its stored data end early)") from None
    except READ_ERRORS as exc:
        why = str(exc) or type(exc).__name__
        raise ValueError(f"{path}: cannot be read ({why})") from None


class Source:
    """Files of a capture, wherever they live."""

    def read(self, path: str) -> Bytes:
        """The whole file."""
        with reading(path):
            return self._read(path, None)

    def read_head(self, path: str, size: int) -> Bytes:
        """The file's first ``size`` bytes (fewer when it is shorter)."""
        with reading(path):
            return self._read(path, size)

    def _read(self, path: str, size: int | None) -> Bytes:
        raise NotImplementedError

    def size_bytes(self, path: str) -> int:
        raise NotImplementedError

    def exists(self, path: str) -> bool:
        raise NotImplementedError

    def list(self) -> list[str]:
        raise NotImplementedError

    def close(self) -> None:
        """Directories hold nothing open."""


class DirSource(Source):
    """A capture directory on disk."""

    def __init__(self, root: Path) -> None:
        self.root = root
        # Joined as strings: a replay opens every file of every frame (and open_capture
        # checks each one's header first), and pathlib's parsing cost more than the reads.
        self._prefix = os.path.join(root, "")

    def _read(self, path: str, size: int | None) -> Bytes:
        with open(self._prefix + path, "rb") as f:
            return f.read() if size is None else f.read(size)

    def size_bytes(self, path: str) -> int:
        with reading(path):
            return os.stat(self._prefix + path).st_size

    def exists(self, path: str) -> bool:
        return os.path.isfile(self._prefix + path)

    def list(self) -> list[str]:
        with reading(f"{self.root.name}/"):
            return [p.relative_to(self.root).as_posix() for p in self.root.rglob("*")
                    if p.is_file()]


class ZipSource(Source):
    """A capture inside an open zip, under ``prefix`` (the folder holding capture.json)."""

    def __init__(self, archive: zipfile.ZipFile, prefix: str, names: list[str]) -> None:
        self.archive = archive
        self.prefix = prefix
        self.names = {n[len(prefix):] for n in names if n.startswith(prefix)}

    def _read(self, path: str, size: int | None) -> Bytes:
        # Reading to the end makes zipfile check the entry's CRC; a head read cannot.
        info = self.archive.getinfo(self.prefix + path)
        with self.archive.open(info) as f:
            return _read_whole(f, info.file_size) if size is None else f.read(size)

    def size_bytes(self, path: str) -> int:
        return self.archive.getinfo(self.prefix + path).file_size

    def exists(self, path: str) -> bool:
        return path in self.names

    def list(self) -> list[str]:
        return sorted(self.names)

    def close(self) -> None:
        self.archive.close()


def _read_whole(file: IO[bytes], size_bytes: int) -> bytearray:
    """The whole entry in one buffer of its size, filled in chunks: zipfile's own read() joins
    its pieces into a second copy, twice the memory for a moment."""
    buffer = bytearray(size_bytes)
    view = memoryview(buffer)
    filled = 0
    while chunk := file.read(min(_CHUNK_BYTES, size_bytes - filled) or 1):
        if filled + len(chunk) > size_bytes:
            raise zipfile.BadZipFile("the entry holds more data than its size says")
        view[filled:filled + len(chunk)] = chunk
        filled += len(chunk)
    if filled != size_bytes:
        raise EOFError
    return buffer


def open_zip(path: Path, limits: ArchiveLimits) -> ZipSource:
    """The capture inside a zip, after checking its directory against ``limits``."""
    try:
        archive = zipfile.ZipFile(path)
    except _OPEN_ERRORS as exc:
        raise ValueError(f"{path.name}: not a readable zip archive ({exc})") from None
    try:
        names = _checked_names(archive, path.name, limits)
        return ZipSource(archive, _capture_prefix(names, path.name), names)
    except ValueError:
        archive.close()
        raise


def _checked_names(archive: zipfile.ZipFile, zip_name: str, limits: ArchiveLimits) -> list[str]:
    infos = archive.infolist()
    if len(infos) > limits.max_files:
        raise ValueError(f"{zip_name}: {len(infos)} entries, more than the limit "
                         f"{limits.max_files}")
    total = 0
    names = []
    for info in infos:
        name = info.filename
        if name.startswith(("/", "\\")) or re.match(r"^[A-Za-z]:", name) or "\\" in name:
            raise ValueError(f"{zip_name}: entry {name!r} has an absolute path")
        if ".." in PurePosixPath(name).parts:
            raise ValueError(f"{zip_name}: entry {name!r} escapes the archive (path traversal)")
        if info.is_dir():
            continue
        total += info.file_size
        if total > limits.max_unpacked_bytes:
            raise ValueError(f"{zip_name}: unpacks to more than {limits.max_unpacked_bytes} bytes")
        if info.file_size > 1024 * 1024 and (
                info.file_size > limits.max_compression_ratio * max(info.compress_size, 1)):
            raise ValueError(f"{zip_name}: entry {name!r} is compressed over "
                             f"{limits.max_compression_ratio:.0f}:1 (zip bomb?)")
        names.append(name)
    return names


def _capture_prefix(names: list[str], zip_name: str) -> str:
    """The folder holding capture.json: the top, or exactly one top folder."""
    if "capture.json" in names:
        return ""
    tops = [n for n in names if n.count("/") == 1 and n.endswith("/capture.json")]
    if len(tops) != 1:
        raise ValueError(f"{zip_name}: no capture.json at the top (or under one top folder)")
    return tops[0][: -len("capture.json")]
