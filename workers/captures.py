"""Captures on the worker's side: a local copy of the stored zip, the reader's limits from the
settings, and reading one whole to validate a fresh upload."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

from celery.exceptions import SoftTimeLimitExceeded

from workers.context import WorkerContext
from workers.settings import Settings

if TYPE_CHECKING:
    from pipeline.io.capture_io import ArchiveLimits

log = logging.getLogger(__name__)


def capture_path(ctx: WorkerContext, sha256: str, key: str) -> Path:
    """A local path of the stored capture zip (a cached copy when storage is remote)."""
    local = ctx.storage.local_path(key)
    if local is not None:
        return local
    cached = ctx.settings.cache_dir / "captures" / f"{sha256}.zip"
    if not cached.is_file():
        ctx.storage.get_to_path(key, cached)
    return cached


def capture_limits(settings: Settings) -> ArchiveLimits:
    """The reader's limits: the same the gateway checked the upload against."""
    from pipeline.io.capture_io import ArchiveLimits

    return ArchiveLimits(max_files=settings.max_capture_files,
                         max_unpacked_bytes=settings.max_unpacked_bytes,
                         max_compression_ratio=settings.max_compression_ratio,
                         max_image_pixels=settings.max_image_pixels)


def read_whole(path: Path, limits: ArchiveLimits) -> tuple[int, tuple[int, ...]]:
    """Opens a capture and decodes every image, one at a time (so memory holds one image,
    not a frame); returns (cameras, frame indices). ValueError names what is wrong."""
    from pipeline.io.capture_io import open_capture

    with open_capture(path, limits) as reader:
        for frame in reader.meta.frame_indices:
            for camera_id in reader.meta.camera_ids:
                reader.read_view(camera_id, frame)
        return len(reader.meta.cameras), reader.meta.frame_indices


def validate_capture(ctx: WorkerContext, capture_id: str) -> None:
    """Read the whole capture (every image decoded); mark it ready or rejected with why.

    Any failure of the reader rejects the capture, so none stays ``validating``; fetching it
    from storage is left to fail the task, whose retries cover a storage hiccup.
    """
    found = ctx.store.capture(capture_id)
    if found is None:
        return  # the upload was abandoned meanwhile
    path = capture_path(ctx, *found)
    try:
        cameras, frame_indices = read_whole(path, capture_limits(ctx.settings))
    except ValueError as exc:
        ctx.store.capture_rejected(capture_id, str(exc))
        return
    except SoftTimeLimitExceeded:
        raise  # the task says how long it took
    except Exception as exc:  # a reader bug, a decoder out of memory: still a clear answer
        log.exception("reading capture %s failed unexpectedly", capture_id)
        ctx.store.capture_rejected(capture_id, f"the capture could not be read "
                                   f"({type(exc).__name__}: {exc})")
        return
    ctx.store.capture_validated(capture_id, cameras, frame_indices)
