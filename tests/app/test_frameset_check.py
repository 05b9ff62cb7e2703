"""check_frame_set reads stored entries in place: a damaged byte anywhere in an entry, a body
cut short, or a local header that names another entry is refused naming the entry; deflated
entries go through zipfile as before."""

from __future__ import annotations

import io
import zipfile

import pytest

from app.core.framesets import check_frame_set
from app.core.problems import ProblemError
from tests.frame_sets import CAMERAS, HEIGHT, WIDTH, frame_entries, pack

SIZES = {camera: (WIDTH, HEIGHT) for camera in CAMERAS}
NAME = "cam1/depth/000000.png"


def _data_start(body: bytes, name: str) -> int:
    info = zipfile.ZipFile(io.BytesIO(body)).getinfo(name)
    return info.header_offset + 30 + len(name)


def _check(body: bytes | bytearray) -> None:
    check_frame_set(bytes(body), 0, SIZES, 10**8)


def test_a_whole_frame_set_passes_stored_or_deflated() -> None:
    _check(pack(frame_entries(0, color=True)))
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
        for name, data in frame_entries(0).items():
            archive.writestr(name, data)
    _check(buffer.getvalue())


def test_a_damaged_byte_past_the_header_is_refused() -> None:
    body = bytearray(pack(frame_entries(0)))
    body[_data_start(bytes(body), NAME) + len(frame_entries(0)[NAME]) - 1] ^= 0xFF
    with pytest.raises(ProblemError, match=f"'{NAME}' is damaged .*CRC"):
        _check(body)


def test_a_local_header_naming_another_entry_is_refused() -> None:
    body = bytearray(pack(frame_entries(0)))
    start = _data_start(bytes(body), NAME) - len(NAME)
    body[start:start + len(NAME)] = NAME.replace("cam1", "cam9").encode()
    with pytest.raises(ProblemError, match=f"'{NAME}' is damaged .*names another"):
        _check(body)


def test_an_entry_whose_header_is_elsewhere_is_refused() -> None:
    body = bytearray(pack(frame_entries(0)))
    body[_data_start(bytes(body), NAME) - len(NAME) - 30] ^= 0xFF  # the local signature
    with pytest.raises(ProblemError, match=f"'{NAME}' is damaged .*no local header"):
        _check(body)
