"""Receiving a capture upload: streamed to a temporary file, hashed on the way, size-limited.

The body never sits whole in memory: chunks go to ``data_dir/tmp`` as they arrive, so the
gateway's memory does not grow with the upload. Both a raw ``application/zip`` body and a
``multipart/form-data`` field named ``file`` are accepted (the multipart body is parsed as a
stream, not spooled first).
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import logging
import os
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import IO

from python_multipart.exceptions import MultipartParseError
from python_multipart.multipart import MultipartParser, parse_options_header
from starlette.requests import ClientDisconnect, Request
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app.core.metrics import UPLOAD_BYTES_KEY
from app.core.problems import ProblemError

ZIP_TYPES = frozenset({"application/zip", "application/x-zip-compressed",
                       "application/octet-stream"})
MULTIPART_TYPE = "multipart/form-data"
FILE_FIELD = "file"
_MAX_PART_HEADERS = 16
_MAX_SWEEP_INTERVAL_S = 60.0

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ReceivedUpload:
    """A complete upload on local disk (the caller moves or deletes it)."""

    path: Path
    sha256: str
    size_bytes: int


class _Sink:
    """Writes the file's bytes, hashing and counting, refusing to pass the limit."""

    def __init__(self, out: IO[bytes], limit: int) -> None:
        self.out = out
        self.limit = limit
        self.digest = hashlib.sha256()
        self.size = 0

    def write(self, data: bytes | memoryview) -> None:
        self.size += len(data)
        if self.size > self.limit:
            raise ProblemError(413, f"The capture is larger than the limit of {self.limit} bytes "
                               "(VOLUMESH_MAX_UPLOAD_BYTES).", kind="upload-too-large")
        self.digest.update(data)
        self.out.write(data)


class _MultipartFile:
    """Feeds a multipart body to python-multipart, sending the ``file`` part to the sink."""

    def __init__(self, boundary: bytes, sink: _Sink) -> None:
        self.sink = sink
        self.header_field = b""
        self.header_value = b""
        self.headers: dict[bytes, bytes] = {}
        self.in_file = False
        self.file_parts = 0
        self.ended = False
        self.parser = MultipartParser(boundary, {
            "on_part_begin": self._part_begin,
            "on_header_field": self._header_field,
            "on_header_value": self._header_value,
            "on_header_end": self._header_end,
            "on_headers_finished": self._headers_finished,
            "on_part_data": self._part_data,
            "on_end": self._end,
        }, max_header_count=_MAX_PART_HEADERS)

    def _part_begin(self) -> None:
        self.headers = {}
        self.in_file = False

    def _header_field(self, data: bytes, start: int, end: int) -> None:
        self.header_field += data[start:end]

    def _header_value(self, data: bytes, start: int, end: int) -> None:
        self.header_value += data[start:end]

    def _header_end(self) -> None:
        self.headers[self.header_field.lower()] = self.header_value
        self.header_field = b""
        self.header_value = b""

    def _headers_finished(self) -> None:
        _, options = parse_options_header(self.headers.get(b"content-disposition", b""))
        if options.get(b"name") == FILE_FIELD.encode():
            self.file_parts += 1
            if self.file_parts > 1:
                raise ProblemError(400, f"The form has more than one '{FILE_FIELD}' field; "
                                   "send one capture zip per request.")
            self.in_file = True

    def _part_data(self, data: bytes, start: int, end: int) -> None:
        if self.in_file:
            self.sink.write(memoryview(data)[start:end])

    def _end(self) -> None:
        self.ended = True

    def feed(self, chunk: bytes) -> None:
        try:
            self.parser.write(chunk)
        except MultipartParseError as exc:
            raise ProblemError(400, f"The multipart body is malformed: {exc}.") from None

    def finish(self) -> None:
        if not self.ended:
            raise ProblemError(400, "The multipart body ended before its closing boundary "
                               "(a truncated upload?).")
        if self.file_parts == 0:
            raise ProblemError(400, f"The form has no '{FILE_FIELD}' field; send the capture "
                               f"zip as a file field named '{FILE_FIELD}'.")


def _media_type(request: Request) -> tuple[str, dict[bytes, bytes]]:
    raw = request.headers.get("content-type", "")
    media, options = parse_options_header(raw)
    return media.decode("latin-1").lower(), options


def _declared_length(request: Request, limit: int) -> None:
    raw = request.headers.get("content-length")
    if raw is None:
        return
    if not raw.isdigit():
        raise ProblemError(400, f"Content-Length {raw!r} is not a number of bytes.")
    if int(raw) > limit:
        raise ProblemError(413, f"The body of {int(raw)} bytes is larger than the limit of "
                           f"{limit} bytes (VOLUMESH_MAX_UPLOAD_BYTES).", kind="upload-too-large")


async def receive_upload(request: Request, tmp_dir: Path, limit: int) -> ReceivedUpload:
    """Stream the request's capture zip to a file in ``tmp_dir``; problems for bad bodies."""
    media, options = _media_type(request)
    multipart: _MultipartFile | None = None
    if media == MULTIPART_TYPE:
        boundary = options.get(b"boundary")
        if not boundary:
            raise ProblemError(400, "The multipart/form-data Content-Type has no boundary.")
    elif media not in ZIP_TYPES:
        shown = media or "none"
        raise ProblemError(415, f"Content-Type {shown!r} is not accepted: send the capture as "
                           "application/zip, or as multipart/form-data with a 'file' field.",
                           kind="unsupported-media-type")
    _declared_length(request, limit + (64 * 1024 if multipart is None else 0))
    tmp_dir.mkdir(parents=True, exist_ok=True)
    path = tmp_dir / f"upload-{uuid.uuid4().hex}.part"
    try:
        with path.open("wb") as out:
            sink = _Sink(out, limit)
            if media == MULTIPART_TYPE:
                multipart = _MultipartFile(options[b"boundary"], sink)
            async for chunk in request.stream():
                if multipart is not None:
                    multipart.feed(chunk)
                elif chunk:
                    sink.write(chunk)
            if multipart is not None:
                multipart.finish()
        if sink.size == 0:
            raise ProblemError(400, "The capture zip is empty (0 bytes).", kind="empty-upload")
        # Counted by the metrics middleware only if the request ends accepted (2xx).
        setattr(request.state, UPLOAD_BYTES_KEY, sink.size)
        return ReceivedUpload(path=path, sha256=sink.digest.hexdigest(), size_bytes=sink.size)
    except ClientDisconnect:
        _discard(path)
        raise ProblemError(400, "The client disconnected before the upload finished; "
                           "nothing was stored.", kind="upload-interrupted") from None
    except asyncio.CancelledError:
        # The server is stopping (its graceful-shutdown time ran out mid-upload): answer with
        # a retryable error rather than letting the server send a bare 500.
        _discard(path)
        raise ProblemError(503, "The gateway stopped while receiving the upload; nothing was "
                           "stored. Upload the capture again.", kind="upload-interrupted",
                           headers={"Retry-After": "5"}) from None
    except BaseException:
        _discard(path)
        raise


def _discard(path: Path) -> None:
    with contextlib.suppress(FileNotFoundError):
        os.unlink(path)


def clean_stale_uploads(tmp_dir: Path, older_than_s: float) -> int:
    """Delete partial uploads untouched for ``older_than_s`` (left by a gateway that died
    mid-upload; a live upload is written continuously, so it stays fresh); returns how many."""
    removed = 0
    if not tmp_dir.is_dir():
        return 0
    deadline = time.time() - older_than_s
    for part in tmp_dir.glob("upload-*.part"):
        with contextlib.suppress(FileNotFoundError):
            if part.stat().st_mtime < deadline:
                _discard(part)
                removed += 1
    return removed


async def sweep_stale_uploads(tmp_dir: Path, older_than_s: float) -> None:
    """Delete stale partial uploads every ``older_than_s / 4`` (at most a minute apart) until
    cancelled, so a gateway that runs for weeks does not keep them until its next restart."""
    interval_s = min(older_than_s / 4, _MAX_SWEEP_INTERVAL_S)
    while True:
        await asyncio.sleep(interval_s)
        try:
            removed = await asyncio.to_thread(clean_stale_uploads, tmp_dir, older_than_s)
        except OSError:  # a passing file-system error must not end the sweeping for good
            log.warning("could not sweep partial uploads in %s", tmp_dir, exc_info=True)
            continue
        if removed:
            log.info("removed %d stale partial uploads", removed)


class BodyIdleTimeoutMiddleware:
    """408 for a request whose body stops arriving: no bytes for ``idle_timeout_s`` while more
    are due (a client that declared a large body, sent a little and stalled).

    The problem is raised from ``receive``, so the reader (``receive_upload``) deletes its
    partial file on the way out; ``Connection: close`` drops the half-sent body. Once the body
    is complete, ``receive`` is passed through untimed (streaming answers wait on it for the
    client's disconnect).
    """

    def __init__(self, app: ASGIApp, idle_timeout_s: float) -> None:
        self.app = app
        self.idle_timeout_s = idle_timeout_s

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        body_done = False

        async def timed() -> Message:
            nonlocal body_done
            if body_done:
                return await receive()
            try:
                # asyncio.timeout, not wait_for: no task per chunk (a frame-set of 4.4 MB
                # arrives in ~18 of them, 30 times a second).
                async with asyncio.timeout(self.idle_timeout_s):
                    message = await receive()
            except TimeoutError:
                raise ProblemError(
                    408, f"No bytes of the request body arrived for {self.idle_timeout_s:g} s "
                    "(VOLUMESH_UPLOAD_IDLE_TIMEOUT_S); nothing was stored. Send the body again.",
                    kind="body-timeout", headers={"Connection": "close"}) from None
            body_done = message["type"] != "http.request" or not message.get("more_body")
            return message

        await self.app(scope, timed, send)
