"""Captures on the worker's side: a local copy of the stored zip, and reading one whole to
validate a fresh upload."""

from __future__ import annotations

from pathlib import Path

from workers.context import WorkerContext


def capture_path(ctx: WorkerContext, sha256: str, key: str) -> Path:
    """A local path of the stored capture zip (a cached copy when storage is remote)."""
    local = ctx.storage.local_path(key)
    if local is not None:
        return local
    cached = ctx.settings.cache_dir / "captures" / f"{sha256}.zip"
    if not cached.is_file():
        ctx.storage.get_to_path(key, cached)
    return cached


def validate_capture(ctx: WorkerContext, capture_id: str) -> None:
    """Read the whole capture (every image decoded); mark it ready or rejected with why."""
    from pipeline.io.capture_io import open_capture

    found = ctx.store.capture(capture_id)
    if found is None:
        return  # the upload was abandoned meanwhile
    sha256, key = found
    try:
        with open_capture(capture_path(ctx, sha256, key)) as reader:
            for frame in reader.meta.frame_indices:
                reader.read_frame(frame)
            cameras, frames = len(reader.meta.cameras), len(reader.meta.frames)
    except ValueError as exc:
        ctx.store.capture_rejected(capture_id, str(exc))
        return
    ctx.store.capture_validated(capture_id, cameras, frames)
