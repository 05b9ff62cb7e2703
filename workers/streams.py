"""Assembling a closed stream: its stored frame-sets, in index order, into one capture zip in
format v1, read whole like an upload and stored as a capture of the stream's owner.

The zip is written to a temporary file one entry at a time (never the sequence in memory).
Its entries carry a fixed time, so the same frame-sets always give the same bytes: a run that
was killed midway and runs again stores the same capture (stored once per content), and a
second delivery finds the stream closed and does nothing. The frame-sets are deleted only once
the stream is closed or failed.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import shutil
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sqlalchemy import select, update

from workers.capture_registry import CaptureZip, register_capture
from workers.captures import capture_limits, read_whole
from workers.context import WorkerContext
from workers.models import Stream, StreamFrame, utcnow
from workers.storage import CHUNK_BYTES

CAPTURE_FORMAT = "volumesh.capture/1"  # docs/capture-format.md
PREVIEW_NAME = "preview.bin"
"""A frame-set's live preview: relayed to viewers, not part of the capture."""
FINAL_STATES = ("closed", "failed")
_ENTRY_TIME = (1980, 1, 1, 0, 0, 0)
_ENTRY_MODE = 0o644 << 16


@dataclass(frozen=True)
class StreamView:
    """A detached copy of the stream fields the assembly needs."""

    id: str
    owner: str
    state: str
    depth_scale: float
    cameras: list[dict[str, Any]]


@dataclass(frozen=True)
class FrameRow:
    index: int
    timestamp_us: int
    storage_key: str


def chunk_prefix(stream_id: str) -> str:
    """The folder of a stream's stored frame-sets (``streams/{id}/{index:06d}.zip``)."""
    return f"streams/{stream_id}/"


def _load(ctx: WorkerContext, stream_id: str) -> StreamView | None:
    with ctx.store.sessions() as session:
        row = session.get(Stream, stream_id)
        if row is None:
            return None
        return StreamView(row.id, row.owner, row.state, row.depth_scale, list(row.cameras))


def _frames(ctx: WorkerContext, stream_id: str) -> list[FrameRow]:
    with ctx.store.sessions() as session:
        rows = session.execute(
            select(StreamFrame.frame_index, StreamFrame.timestamp_us, StreamFrame.storage_key)
            .where(StreamFrame.stream_id == stream_id).order_by(StreamFrame.frame_index))
        return [FrameRow(index, timestamp_us, key) for index, timestamp_us, key in rows]


def finish_stream(ctx: WorkerContext, stream_id: str, *, capture_id: str | None = None,
                  error: str | None = None) -> bool:
    """Mark an assembling stream closed (with its capture) or failed (with why); True for
    the call that did."""
    state = "failed" if error is not None else "closed"
    with ctx.store.sessions.begin() as session:
        result = session.execute(
            update(Stream).where(Stream.id == stream_id, Stream.state == "assembling")
            .values(state=state, capture_id=capture_id,
                    error=None if error is None else error[:4000], updated_at=utcnow()))
        return bool(result.rowcount)  # type: ignore[attr-defined]


def delete_chunks_if_over(ctx: WorkerContext, stream_id: str) -> None:
    """Delete the stream's frame-sets once it is closed or failed (never while a client may
    still send them, or a worker assemble them)."""
    with ctx.store.sessions() as session:
        state = session.scalar(select(Stream.state).where(Stream.id == stream_id))
    if state in FINAL_STATES:
        ctx.storage.delete_prefix(chunk_prefix(stream_id))


def _entry(name: str, size_bytes: int = 0) -> zipfile.ZipInfo:
    info = zipfile.ZipInfo(name, date_time=_ENTRY_TIME)
    info.compress_type = zipfile.ZIP_STORED
    info.external_attr = _ENTRY_MODE
    info.file_size = size_bytes  # tells zipfile up front whether the entry needs zip64
    return info


@contextlib.contextmanager
def _work_dir(ctx: WorkerContext, stream_id: str) -> Iterator[Path]:
    """The run's folder of temporary files, emptied first: what a run killed midway left there
    goes when its task runs again. One run at a time assembles a stream (its task is queued
    once, and handed to another worker only when its worker died)."""
    folder = ctx.settings.tmp_dir / "streams" / stream_id
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    try:
        yield folder
    finally:
        shutil.rmtree(folder, ignore_errors=True)


@contextlib.contextmanager
def _local_chunk(ctx: WorkerContext, key: str, work_dir: Path) -> Iterator[Path]:
    """A local path of a stored frame-set (a temporary copy when storage is remote)."""
    local = ctx.storage.local_path(key)
    if local is not None:
        yield local
        return
    copy = work_dir / "frame-set.zip"
    try:
        ctx.storage.get_to_path(key, copy)
        yield copy
    finally:
        copy.unlink(missing_ok=True)


def _capture_json(stream: StreamView, frames: list[FrameRow]) -> bytes:
    document = {"format": CAPTURE_FORMAT, "depth_scale": stream.depth_scale,
                "cameras": stream.cameras,
                "frames": [{"index": f.index, "timestamp_us": f.timestamp_us} for f in frames]}
    return json.dumps(document, indent=1).encode()


def _copy_frame_set(source: zipfile.ZipFile, out: zipfile.ZipFile) -> None:
    for info in sorted(source.infolist(), key=lambda i: i.filename):
        if info.filename == PREVIEW_NAME:
            continue
        with source.open(info) as src, out.open(_entry(info.filename, info.file_size),
                                                "w") as dst:
            shutil.copyfileobj(src, dst, CHUNK_BYTES)


def write_capture_zip(ctx: WorkerContext, stream: StreamView, frames: list[FrameRow],
                      path: Path) -> CaptureZip:
    """capture.json, then every frame-set's images in index order, stored (no compression:
    the images are compressed already), hashed once written."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED, allowZip64=True) as out:
        out.writestr(_entry("capture.json"), _capture_json(stream, frames))
        for frame in frames:
            with (_local_chunk(ctx, frame.storage_key, path.parent) as chunk_path,
                  zipfile.ZipFile(chunk_path) as source):
                _copy_frame_set(source, out)
    digest = hashlib.sha256()
    with path.open("rb") as written:
        while block := written.read(CHUNK_BYTES):
            digest.update(block)
    return CaptureZip(path, digest.hexdigest(), path.stat().st_size)


def assemble_stream(ctx: WorkerContext, stream_id: str) -> None:
    """Assemble an `assembling` stream into a capture, then delete its frame-sets; a stream
    in another state is left as it is."""
    stream = _load(ctx, stream_id)
    if stream is None or stream.state != "assembling":
        if stream is not None:  # a run killed between closing the stream and the deletion
            delete_chunks_if_over(ctx, stream_id)
        return
    with _work_dir(ctx, stream_id) as work_dir:
        zipped = write_capture_zip(ctx, stream, _frames(ctx, stream_id),
                                   work_dir / "capture.zip")
        try:
            cameras, frame_indices = read_whole(zipped.path, capture_limits(ctx.settings))
        except ValueError as exc:
            finish_stream(ctx, stream_id, error=f"the assembled capture is not valid: {exc}")
        else:
            registered = register_capture(ctx.store.sessions, ctx.storage, zipped,
                                          stream.owner, ctx.settings.validation_timeout_s)
            ctx.store.capture_validated(registered.capture_id, cameras, frame_indices)
            finish_stream(ctx, stream_id, capture_id=registered.capture_id)
    delete_chunks_if_over(ctx, stream_id)
