"""The one-pass stored zip reads back through zipfile: names, bytes, CRCs, dates; a damaged
byte fails zipfile's CRC check as it would for zipfile's own archive."""

from __future__ import annotations

import io
import os
import time
import zipfile

import pytest

from agent.stored_zip import stored_zip

ENTRIES = [("a/depth/000007.png", os.urandom(70_000)), ("a/color/000007.jpg", b""),
           ("b/depth/000007.png", b"x" * 3), ("café/preview.bin", os.urandom(1000))]


def test_zipfile_reads_every_entry_with_its_crc() -> None:
    data = stored_zip(ENTRIES, epoch_s=time.mktime((2026, 11, 28, 15, 47, 30, 0, 0, -1)))
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        assert archive.testzip() is None  # every entry's CRC checked
        assert [(i.filename, archive.read(i)) for i in archive.infolist()] == ENTRIES
        for info in archive.infolist():
            assert info.compress_type == zipfile.ZIP_STORED
            assert info.date_time == (2026, 11, 28, 15, 47, 30)
            assert info.external_attr >> 16 == 0o600


def test_an_empty_zip_is_a_zip() -> None:
    with zipfile.ZipFile(io.BytesIO(stored_zip([]))) as archive:
        assert archive.namelist() == []


def test_a_damaged_entry_fails_the_crc_check() -> None:
    data = bytearray(stored_zip(ENTRIES))
    data[30 + len(ENTRIES[0][0]) + 100] ^= 0xFF  # a byte inside the first entry
    with zipfile.ZipFile(io.BytesIO(bytes(data))) as archive, \
            pytest.raises(zipfile.BadZipFile, match="CRC"):
        archive.read(ENTRIES[0][0])
