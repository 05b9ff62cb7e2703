"""Zip-level checks of an uploaded capture, done by the gateway before anything is stored.

The gateway does not import the capture reader (it lives in ``pipeline``); it refuses here what
can be refused from the zip's directory alone (not a zip, too many entries, too large unpacked,
zip bombs, path traversal, links, encryption) and leaves the capture format to a worker.
"""

from __future__ import annotations

import re
import stat
import zipfile
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

from app.core.problems import ProblemError

_ALLOWED_METHODS = {zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED, zipfile.ZIP_BZIP2,
                    zipfile.ZIP_LZMA}
_LOCAL_HEADER_BYTES = 30
_BOMB_MIN_BYTES = 1024 * 1024


@dataclass(frozen=True)
class ZipLimits:
    max_files: int
    max_unpacked_bytes: int
    max_compression_ratio: float


@dataclass(frozen=True)
class ZipSummary:
    entries: int
    unpacked_bytes: int
    root: str
    """The folder holding capture.json inside the zip ('' at the top)."""


def _bad(detail: str, status: int = 422, kind: str = "invalid-capture-zip") -> ProblemError:
    return ProblemError(status, detail, kind=kind)


def _check_name(name: str) -> None:
    if "\x00" in name or "\\" in name:
        raise _bad(f"Zip entry {name!r} has a backslash or NUL in its name; capture zips use "
                   "'/' separated relative paths.")
    if name.startswith("/") or re.match(r"^[A-Za-z]:", name):
        raise _bad(f"Zip entry {name!r} has an absolute path; capture zips hold relative paths.")
    if ".." in PurePosixPath(name).parts:
        raise _bad(f"Zip entry {name!r} points outside the archive (path traversal).")


def _check_entry(info: zipfile.ZipInfo, limits: ZipLimits) -> None:
    _check_name(info.filename)
    mode = info.external_attr >> 16
    if stat.S_ISLNK(mode):
        raise _bad(f"Zip entry {info.filename!r} is a symbolic link; links are not accepted.")
    if info.flag_bits & 0x1:
        raise _bad(f"Zip entry {info.filename!r} is encrypted; upload an unencrypted zip.")
    if info.compress_type not in _ALLOWED_METHODS:
        raise _bad(f"Zip entry {info.filename!r} uses compression method {info.compress_type}; "
                   "use stored or deflate.")
    if (info.file_size > _BOMB_MIN_BYTES
            and info.file_size > limits.max_compression_ratio * max(info.compress_size, 1)):
        raise _bad(f"Zip entry {info.filename!r} unpacks {info.file_size} bytes from "
                   f"{info.compress_size}, over the {limits.max_compression_ratio:.0f}:1 limit "
                   "(a zip bomb?).", status=413, kind="zip-bomb")


def _check_overlap(infos: list[zipfile.ZipInfo]) -> None:
    # Entries sharing compressed bytes multiply the unpacked size (an overlapping zip bomb).
    ordered = sorted(infos, key=lambda i: i.header_offset)
    for before, after in zip(ordered, ordered[1:], strict=False):
        end = (before.header_offset + _LOCAL_HEADER_BYTES + len(before.orig_filename.encode())
               + before.compress_size)
        if after.header_offset < end:
            raise _bad(f"Zip entries {before.filename!r} and {after.filename!r} overlap "
                       "(a zip bomb?).", status=413, kind="zip-bomb")


def _capture_root(names: list[str]) -> str:
    if "capture.json" in names:
        return ""
    tops = [n for n in names if n.count("/") == 1 and n.endswith("/capture.json")]
    if len(tops) != 1:
        raise _bad("The zip has no capture.json at its top (or under one top folder); is it a "
                   "volumesh capture (docs/capture-format.md)?")
    return tops[0][: -len("capture.json")]


def check_zip(path: Path, limits: ZipLimits) -> ZipSummary:
    """Refuse what the zip directory alone shows to be wrong; ``ProblemError`` says why."""
    try:
        with zipfile.ZipFile(path) as archive:
            infos = archive.infolist()
    except zipfile.BadZipFile as exc:
        raise _bad(f"The body is not a readable zip archive ({exc}); was the upload truncated?",
                   status=400, kind="not-a-zip") from None
    except (OSError, EOFError, ValueError, NotImplementedError) as exc:
        raise _bad(f"The zip archive is damaged ({exc}).", status=400, kind="not-a-zip") from None
    if len(infos) > limits.max_files:
        raise _bad(f"The zip has {len(infos)} entries, more than the limit of "
                   f"{limits.max_files} (VOLUMESH_MAX_CAPTURE_FILES).", status=413,
                   kind="too-many-files")
    names = [info.filename for info in infos]
    if len(set(names)) != len(names):
        raise _bad("The zip holds two entries with the same name.")
    total = 0
    for info in infos:
        _check_entry(info, limits)
        total += info.file_size
        if total > limits.max_unpacked_bytes:
            raise _bad(f"The zip unpacks to more than {limits.max_unpacked_bytes} bytes "
                       "(VOLUMESH_MAX_UNPACKED_BYTES).", status=413, kind="zip-bomb")
    _check_overlap(infos)
    files = [info.filename for info in infos if not info.is_dir()]
    return ZipSummary(entries=len(files), unpacked_bytes=total, root=_capture_root(files))
