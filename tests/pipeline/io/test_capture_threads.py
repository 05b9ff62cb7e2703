"""A capture written by writer threads while the caller reads: the same files as one thread
writes, and an error on either side stops both and is raised (no thread left waiting)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from pipeline.capture import CameraInfo, CaptureMeta, Intrinsics
from pipeline.io.capture_io import StoredView, write_capture
from pipeline.io.capture_threads import QUEUED_VIEWS_PER_WRITER, write_capture_threaded

WIDTH, HEIGHT = 16, 12
VIEWS = 40  # more than the queue holds, so the reader waits for the writers


def _meta() -> CaptureMeta:
    cameras = tuple(CameraInfo(id=f"cam{i}", depth_intrinsics=Intrinsics(
        WIDTH, HEIGHT, 20.0, 20.0, 8.0, 6.0)) for i in range(2))
    return CaptureMeta(depth_scale=0.001, cameras=cameras, frames=())


def _views(meta: CaptureMeta, count: int = VIEWS) -> Iterator[StoredView]:
    rng = np.random.default_rng(0)
    for index in range(count):
        depth = rng.integers(0, 65535, (HEIGHT, WIDTH), dtype=np.uint16)
        yield StoredView(meta.cameras[index % 2], index // 2, depth,
                         color_jpeg=b"\xff\xd8" + bytes([index]) * 7)


def _files(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("writer_threads", [1, 2, 3])
def test_writer_threads_write_what_one_call_writes(tmp_path: Path, writer_threads: int) -> None:
    meta = _meta()
    write_capture(tmp_path / "one", meta, _views(meta))
    write_capture_threaded(tmp_path / "threads", meta, _views(meta), writer_threads)
    assert _files(tmp_path / "threads") == _files(tmp_path / "one")
    assert len(_files(tmp_path / "one")) == 1 + 2 * VIEWS


def test_an_error_while_reading_stops_the_writers_and_is_raised(tmp_path: Path) -> None:
    meta = _meta()

    def failing() -> Iterator[StoredView]:
        yield from _views(meta, 10)
        raise ValueError("device1.mkv: damaged Matroska data")

    with pytest.raises(ValueError, match="damaged"):
        write_capture_threaded(tmp_path, meta, failing(), 2)
    assert len(list(tmp_path.rglob("*.png"))) <= 10


def test_a_writer_error_stops_the_reading_and_is_raised(tmp_path: Path) -> None:
    meta = _meta()
    (tmp_path / "cam1").write_bytes(b"")  # a file where cam1's folder goes: its writes fail
    drawn: list[StoredView] = []

    def counted() -> Iterator[StoredView]:
        for view in _views(meta, 1000):
            drawn.append(view)
            yield view

    with pytest.raises(OSError):
        write_capture_threaded(tmp_path, meta, counted(), 2)
    # The reading stopped soon after: what the queue and the surviving writer took, no more.
    assert len(drawn) < 1000 - 2 * QUEUED_VIEWS_PER_WRITER
