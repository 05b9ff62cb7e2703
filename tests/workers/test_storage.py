"""Storage: a local directory and a real S3-compatible server (moto's, as a process)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from tests.integration.services import MotoS3
from workers.settings import Settings
from workers.storage import LocalStorage, Storage, make_storage


def s3_settings(data_dir: Path, moto: MotoS3) -> Settings:
    return Settings.model_validate({"data_dir": data_dir, **moto.settings("volumesh-test")})


@pytest.fixture(params=["local", "s3"])
def storage(request: pytest.FixtureRequest, tmp_path: Path) -> Storage:
    if request.param == "local":
        return make_storage(Settings(data_dir=tmp_path))
    moto: MotoS3 = request.getfixturevalue("moto")
    return make_storage(s3_settings(tmp_path, moto))


def test_local_by_default_and_s3_by_url(tmp_path: Path, moto: MotoS3) -> None:
    assert isinstance(make_storage(Settings(data_dir=tmp_path)), LocalStorage)
    s3 = make_storage(s3_settings(tmp_path, moto))
    assert type(s3).__name__ == "S3Storage"
    with pytest.raises(ValueError, match="STORAGE_URL"):
        make_storage(Settings(data_dir=tmp_path, storage_url="ftp://host/x"))


def test_round_trip_ranges_and_delete(storage: Storage, tmp_path: Path) -> None:
    data = os.urandom(3 * 1024 * 1024 + 17)
    source = tmp_path / "in.bin"
    source.write_bytes(data)
    storage.put_file("captures/a.zip", source)
    assert source.exists()  # not moved unless asked
    assert storage.exists("captures/a.zip") and storage.size("captures/a.zip") == len(data)
    assert b"".join(storage.iter_range("captures/a.zip", 0, len(data) - 1)) == data
    assert b"".join(storage.iter_range("captures/a.zip", 100, 1_200_000)) == data[100:1_200_001]
    storage.get_to_path("captures/a.zip", tmp_path / "out" / "copy.bin")
    assert (tmp_path / "out" / "copy.bin").read_bytes() == data
    storage.put_bytes("assets/x/report.json", b"{}")
    assert b"".join(storage.iter_range("assets/x/report.json", 0, 1)) == b"{}"
    storage.delete("captures/a.zip")
    assert not storage.exists("captures/a.zip")
    with pytest.raises(FileNotFoundError):
        storage.size("captures/a.zip")
    storage.ping()


def test_move_consumes_the_source(storage: Storage, tmp_path: Path) -> None:
    source = tmp_path / "upload.part"
    source.write_bytes(b"abc")
    storage.put_file("captures/b.zip", source, move=True)
    assert not source.exists()
    assert storage.size("captures/b.zip") == 3


@pytest.mark.parametrize("key", ["", "/abs", "a/../b", "a//b", "./a"])
def test_keys_must_be_plain_relative_paths(storage: Storage, key: str) -> None:
    with pytest.raises(ValueError, match="storage key"):
        storage.put_bytes(key, b"x")


def test_local_writes_are_atomic(tmp_path: Path) -> None:
    storage = LocalStorage(tmp_path / "root")
    storage.put_bytes("k/v.bin", b"old")
    source = tmp_path / "big.bin"
    source.write_bytes(b"new" * 1000)
    storage.put_file("k/v.bin", source)
    assert b"".join(storage.iter_range("k/v.bin", 0, 2999)) == b"new" * 1000
    # A write whose final rename fails (the key is taken by a folder) leaves no partial file.
    (tmp_path / "root" / "k" / "dir.bin").mkdir()
    with pytest.raises(OSError):
        storage.put_file("k/dir.bin", source)
    with pytest.raises(OSError):
        storage.put_bytes("k/dir.bin", b"x" * 10)
    assert sorted(p.name for p in (tmp_path / "root" / "k").iterdir()) == ["dir.bin", "v.bin"]
