"""Where captures and assets are kept: a local directory, or S3-compatible object storage.

Both sides of the service use the same small interface, so workers on other machines read the
captures the gateway stored. Writes are atomic: a reader sees the whole object or none.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Protocol

from workers.settings import Settings

CHUNK_BYTES = 1024 * 1024
ARTIFACTS = "artifacts"
"""Prefix of the stage outputs (``artifacts/<capture sha>/...``, `workers.artifacts`)."""


class Storage(Protocol):
    """Objects by key (``captures/<sha>-<n>.zip``, ``artifacts/<sha>/...``,
    ``assets/<id>/mesh.glb``)."""

    def put_file(self, key: str, path: Path, *, move: bool = False) -> None:
        """Store the file at ``path`` under ``key`` atomically; ``move`` may consume it."""

    def put_bytes(self, key: str, data: bytes) -> None:
        """Store ``data`` under ``key`` atomically."""

    def get_to_path(self, key: str, path: Path) -> None:
        """Copy the object to ``path`` (written atomically)."""

    def local_path(self, key: str) -> Path | None:
        """The object's own file when storage is local (no copy needed), else None."""

    def exists(self, key: str) -> bool: ...

    def size(self, key: str) -> int:
        """Bytes in the object; ``FileNotFoundError`` when absent."""

    def iter_range(self, key: str, start: int, end: int) -> Iterator[bytes]:
        """The bytes ``start`` to ``end`` inclusive, in chunks."""

    def delete(self, key: str) -> None:
        """Remove the object if present."""

    def delete_prefix(self, prefix: str) -> int:
        """Remove every object under the folder ``prefix`` (ends with ``/``); returns how many."""

    def ping(self) -> None:
        """Raise when the storage cannot be reached."""


def _check_key(key: str) -> str:
    parts = key.split("/")
    if not key or key.startswith("/") or any(p in ("", ".", "..") for p in parts):
        raise ValueError(f"storage key {key!r} is not a plain relative path")
    return key


def _check_prefix(prefix: str) -> str:
    if not prefix.endswith("/"):
        raise ValueError(f"storage prefix {prefix!r} must be a folder ending with '/'")
    return _check_key(prefix[:-1])


def atomic_copy(source: Path, target: Path) -> None:
    """Copy ``source`` to ``target`` through a temporary file in the target's folder."""
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=".part-")
    try:
        with os.fdopen(fd, "wb") as out, source.open("rb") as src:
            shutil.copyfileobj(src, out, CHUNK_BYTES)
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


class LocalStorage:
    """Objects as files under a root directory."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.root.mkdir(parents=True, exist_ok=True)

    def _path(self, key: str) -> Path:
        return self.root / _check_key(key)

    def put_file(self, key: str, path: Path, *, move: bool = False) -> None:
        target = self._path(key)
        target.parent.mkdir(parents=True, exist_ok=True)
        if move:
            try:
                os.replace(path, target)  # same file system: a rename, atomic
                return
            except OSError:
                pass
        atomic_copy(path, target)

    def put_bytes(self, key: str, data: bytes) -> None:
        target = self._path(key)
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=".part-")
        try:
            with os.fdopen(fd, "wb") as out:
                out.write(data)
            os.replace(tmp, target)
        except BaseException:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
            raise

    def get_to_path(self, key: str, path: Path) -> None:
        atomic_copy(self._path(key), path)

    def local_path(self, key: str) -> Path | None:
        return self._path(key)

    def exists(self, key: str) -> bool:
        return self._path(key).is_file()

    def size(self, key: str) -> int:
        return self._path(key).stat().st_size

    def iter_range(self, key: str, start: int, end: int) -> Iterator[bytes]:
        with self._path(key).open("rb") as f:
            f.seek(start)
            left = end - start + 1
            while left > 0:
                chunk = f.read(min(CHUNK_BYTES, left))
                if not chunk:
                    return
                left -= len(chunk)
                yield chunk

    def delete(self, key: str) -> None:
        with contextlib.suppress(FileNotFoundError):
            self._path(key).unlink()

    def delete_prefix(self, prefix: str) -> int:
        folder = self._path(_check_prefix(prefix))
        removed = 0
        for path in sorted(folder.rglob("*"), reverse=True):  # files before their folders
            with contextlib.suppress(OSError):  # gone already, or written to meanwhile
                if path.is_dir():
                    path.rmdir()
                else:
                    path.unlink()
                    removed += 1
        with contextlib.suppress(OSError):  # gone already, or written to meanwhile
            folder.rmdir()
        return removed

    def ping(self) -> None:
        if not os.access(self.root, os.W_OK):
            raise OSError(f"storage folder {self.root} is not writable")


class S3Storage:
    """Objects in an S3 bucket under a prefix (any S3-compatible endpoint)."""

    def __init__(self, bucket: str, prefix: str, client: Any) -> None:
        self.bucket = bucket
        self.prefix = prefix.strip("/")
        self.client = client

    def _key(self, key: str) -> str:
        key = _check_key(key)
        return f"{self.prefix}/{key}" if self.prefix else key

    def put_file(self, key: str, path: Path, *, move: bool = False) -> None:
        # An S3 PUT (or a completed multipart upload) is atomic: readers never see a part.
        self.client.upload_file(str(path), self.bucket, self._key(key))
        if move:
            path.unlink(missing_ok=True)

    def put_bytes(self, key: str, data: bytes) -> None:
        self.client.put_object(Bucket=self.bucket, Key=self._key(key), Body=data)

    def get_to_path(self, key: str, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".part-")
        os.close(fd)
        try:
            self.client.download_file(self.bucket, self._key(key), tmp)
            os.replace(tmp, path)
        except BaseException:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
            raise

    def local_path(self, key: str) -> Path | None:
        return None

    def exists(self, key: str) -> bool:
        try:
            self.size(key)
        except FileNotFoundError:
            return False
        return True

    def size(self, key: str) -> int:
        from botocore.exceptions import ClientError

        try:
            head = self.client.head_object(Bucket=self.bucket, Key=self._key(key))
        except ClientError as exc:
            if exc.response.get("Error", {}).get("Code") in ("404", "NoSuchKey", "NotFound"):
                raise FileNotFoundError(key) from exc
            raise
        return int(head["ContentLength"])

    def iter_range(self, key: str, start: int, end: int) -> Iterator[bytes]:
        body = self.client.get_object(
            Bucket=self.bucket, Key=self._key(key), Range=f"bytes={start}-{end}")["Body"]
        try:
            yield from body.iter_chunks(CHUNK_BYTES)
        finally:
            body.close()

    def delete(self, key: str) -> None:
        self.client.delete_object(Bucket=self.bucket, Key=self._key(key))

    def delete_prefix(self, prefix: str) -> int:
        pages = self.client.get_paginator("list_objects_v2").paginate(
            Bucket=self.bucket, Prefix=self._key(_check_prefix(prefix)) + "/")
        removed = 0
        for page in pages:  # at most 1000 keys a page, the most one DeleteObjects takes
            keys = [{"Key": item["Key"]} for item in page.get("Contents", ())]
            if keys:
                self.client.delete_objects(Bucket=self.bucket,
                                           Delete={"Objects": keys, "Quiet": True})
                removed += len(keys)
        return removed

    def ping(self) -> None:
        self.client.head_bucket(Bucket=self.bucket)


def make_storage(settings: Settings) -> Storage:
    """Storage for ``settings.storage_url``: ``s3://bucket/prefix`` or a local directory."""
    url = settings.resolved_storage_url
    if url.startswith("s3://"):
        import boto3
        from botocore.config import Config

        bucket, _, prefix = url[len("s3://"):].partition("/")
        if not bucket:
            raise ValueError(f"VOLUMESH_STORAGE_URL {url!r} names no bucket")
        secret = settings.s3_secret_access_key
        client = boto3.client(
            "s3",
            endpoint_url=settings.s3_endpoint_url,
            region_name=settings.s3_region,
            aws_access_key_id=settings.s3_access_key_id,
            aws_secret_access_key=secret.get_secret_value() if secret else None,
            config=Config(retries={"max_attempts": 5, "mode": "standard"},
                          connect_timeout=5, read_timeout=60),
        )
        return S3Storage(bucket, prefix, client)
    if "://" in url and not url.startswith("file://"):
        raise ValueError(f"VOLUMESH_STORAGE_URL {url!r}: use s3://bucket/prefix or a directory")
    return LocalStorage(Path(url.removeprefix("file://")))
