"""A capture written by threads while the calling thread produces its views.

Reading a recording holds the GIL most of the time (demuxing, matching frames in Python);
encoding a depth PNG and writing files mostly release it (ISA-L's deflate, numpy, the
system calls). So the caller reads while writer threads encode and write, and two cores stay
busy. The writers draw from a bounded queue: memory holds a few views, however fast the
reading.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from queue import Empty, Full, Queue

from pipeline.capture import CaptureMeta
from pipeline.io.capture_io import StoredView, write_capture

QUEUED_VIEWS_PER_WRITER = 4
"""Views waiting per writer thread: with two writers, one frame-set of an eight-camera rig,
which the reader yields in a burst (~7 MB of recorded depth and JPEGs)."""
_FAILED_POLL_S = 0.1
"""How often a reader waiting for room checks whether the writers failed: room that comes
wakes it at once, so this only bounds how long a failure goes unnoticed."""


def write_capture_threaded(out: Path, meta: CaptureMeta, views: Iterator[StoredView],
                           writer_threads: int) -> None:
    """write_capture(out, meta, views) with the images encoded and written by
    ``writer_threads`` threads while this thread draws the views from ``views`` (a generator
    stays in the thread that runs it, so the caller can close it). Each writer is one
    write_capture call (the same capture.json, then the views it takes), so together they
    write what one call would. A writer's error is raised here once the reading stopped; an
    error while reading (or Ctrl-C) stops the writers at their next view and is raised."""
    queue: Queue[StoredView | None] = Queue(maxsize=writer_threads * QUEUED_VIEWS_PER_WRITER)
    stop, failed = threading.Event(), threading.Event()

    def taken() -> Iterator[StoredView]:
        while (view := queue.get()) is not None and not stop.is_set():
            yield view

    def write() -> None:
        try:
            write_capture(out, meta, taken())
        except BaseException:
            failed.set()
            raise

    with ThreadPoolExecutor(writer_threads, thread_name_prefix="capture-writer") as pool:
        calls = [pool.submit(write) for _ in range(writer_threads)]
        try:
            _feed(queue, views, failed, writer_threads)
        except BaseException:
            stop.set()
            _end_now(queue, writer_threads)
            raise
        if failed.is_set():
            stop.set()
            _end_now(queue, writer_threads)
        for call in calls:
            call.result()


def _feed(queue: Queue[StoredView | None], views: Iterator[StoredView],
          failed: threading.Event, writer_threads: int) -> None:
    """Queues every view, then one end mark per writer; stops early where a writer failed."""
    for view in views:
        if not _put(queue, view, failed):
            return
    for _ in range(writer_threads):
        if not _put(queue, None, failed):
            return


def _put(queue: Queue[StoredView | None], item: StoredView | None,
         failed: threading.Event) -> bool:
    """Waits for room and queues ``item``; False where a writer failed meanwhile (the writers
    left may be too few to ever make room)."""
    while not failed.is_set():
        try:
            queue.put(item, timeout=_FAILED_POLL_S)
            return True
        except Full:
            continue
    return False


def _end_now(queue: Queue[StoredView | None], writer_threads: int) -> None:
    """Drops the views not yet taken and queues an end mark per writer: each writer then
    ends at its next view, whether or not others have failed. Only the caller's thread
    queues, so once emptied the queue has room for every mark."""
    while True:
        try:
            queue.get_nowait()
        except Empty:
            break
    for _ in range(writer_threads):
        queue.put_nowait(None)
