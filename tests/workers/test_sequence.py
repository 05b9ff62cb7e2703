"""Sequence jobs in the job store: each frame counted once, the export claimed exactly once
(frames ending together from many threads), the manifest and its frame rate."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import pytest

from app.web import SequenceManifest
from workers.db import init_db, make_engine, make_sessionmaker
from workers.jobstore import JobStore
from workers.models import Capture, Job
from workers.sequence import SEQUENCE_STAGES, count_ended_frames, frame_over
from workers.sequence_export import (
    DEFAULT_FPS,
    FrameOutcome,
    build_manifest,
    fps_from_timestamps,
)
from workers.settings import Settings

PARENT = "p" * 32


@pytest.fixture
def store(store_settings: Settings) -> JobStore:
    return _store(store_settings)


def _store(settings: Settings) -> JobStore:
    engine = make_engine(settings)
    init_db(engine)
    return JobStore(make_sessionmaker(engine))


def _sequence(store: JobStore, frames: int) -> list[str]:
    """A running sequence job with ``frames`` frame jobs; their ids."""
    ids = [f"{i:032x}" for i in range(frames)]
    with store.sessions.begin() as session:
        session.add(Capture(id="c" * 32, sha256="c" * 64, size_bytes=1, storage_key="k",
                            state="ready"))
        session.add(Job(id=PARENT, capture_id="c" * 32, state="running",
                        stages=list(SEQUENCE_STAGES), stage=SEQUENCE_STAGES[0],
                        frames_total=frames, frames_done=0, frames_failed=0))
        session.add_all([Job(id=i, capture_id="c" * 32, parent_id=PARENT, frame_index=n)
                         for n, i in enumerate(ids)])
    return ids


class Sent:
    def __init__(self) -> None:
        self.calls: list[tuple[str, list[Any], str]] = []
        self.lock = threading.Lock()

    def __call__(self, name: str, args: list[Any], queue: str) -> str:
        with self.lock:
            self.calls.append((name, args, queue))
        return "task"


def _end(store: JobStore, job_id: str, state: str, error: str | None = None) -> None:
    with store.sessions.begin() as session:
        job = session.get(Job, job_id)
        assert job is not None
        job.state, job.error = state, error


def test_the_last_frame_queues_the_export_once(store: JobStore) -> None:
    ids = _sequence(store, 3)
    sent = Sent()
    _end(store, ids[0], "succeeded")
    assert not frame_over(store.sessions, ids[0], sent)
    assert not frame_over(store.sessions, ids[0], sent)  # a second call counts nothing
    _end(store, ids[1], "failed", "depth: every pixel is zero")
    assert not frame_over(store.sessions, ids[1], sent)
    assert not frame_over(store.sessions, ids[2], sent)  # still running: not over
    _end(store, ids[2], "succeeded")
    assert frame_over(store.sessions, ids[2], sent)
    assert not frame_over(store.sessions, ids[2], sent)
    assert sent.calls == [("volumesh.sequence", [PARENT], "cpu")]
    with store.sessions() as session:
        parent = session.get(Job, PARENT)
        assert parent is not None
        assert (parent.frames_done, parent.frames_failed, parent.stage) == (2, 1, "export")
        assert parent.frame_errors == {"1": "depth: every pixel is zero"}


def test_frames_ending_together_queue_the_export_exactly_once(store: JobStore) -> None:
    ids = _sequence(store, 12)
    for job_id in ids:
        _end(store, job_id, "succeeded")
    sent = Sent()
    barrier = threading.Barrier(len(ids))

    def finish(job_id: str) -> None:
        barrier.wait()
        frame_over(store.sessions, job_id, sent)
        frame_over(store.sessions, job_id, sent)  # a redelivery

    threads = [threading.Thread(target=finish, args=(i,)) for i in ids]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert sent.calls == [("volumesh.sequence", [PARENT], "cpu")]
    with store.sessions() as session:
        parent = session.get(Job, PARENT)
        assert parent is not None and (parent.frames_done, parent.frames_failed) == (12, 0)


def test_a_top_level_job_is_no_frame(store: JobStore) -> None:
    _sequence(store, 1)
    _end(store, PARENT, "failed")
    assert not frame_over(store.sessions, PARENT, Sent())


def test_frame_rate_comes_from_the_timestamps() -> None:
    assert fps_from_timestamps([0, 33_333, 66_666, 100_000]) == pytest.approx(30.0, abs=0.01)
    assert fps_from_timestamps([0, 40_000, 120_000, 160_000]) == 25.0  # a dropped frame
    assert fps_from_timestamps([0, 0, 0]) == DEFAULT_FPS
    assert fps_from_timestamps([5]) == DEFAULT_FPS


def test_the_manifest_is_what_the_viewer_plays() -> None:
    frames = [FrameOutcome("a" * 32, 0, "succeeded", "a" * 32, None),
              FrameOutcome("b" * 32, 1, "failed", None, "depth: every pixel is zero"),
              FrameOutcome("c" * 32, 2, "succeeded", "c" * 32, None)]
    reports = {"a" * 32: {"bounds_m": [[-1, 0, -1], [1, 2, 1]], "triangles": 10},
               "c" * 32: {"bounds_m": [[-2, 0.5, -1], [0, 1, 3]], "triangles": 12}}
    manifest = SequenceManifest.model_validate(build_manifest(30.0, frames, reports))
    assert [f.url for f in manifest.frames] == [f"../{'a' * 32}/mesh.glb",
                                                f"../{'c' * 32}/mesh.glb"]
    assert manifest.bounds.min == (-2, 0, -1) and manifest.bounds.max == (1, 2, 3)
    failed = manifest.model_dump()["failed_frames"]
    assert failed == [{"frame_index": 1, "job_id": "b" * 32,
                       "error": "depth: every pixel is zero"}]


def test_a_failed_send_leaves_the_frame_to_count_again(store: JobStore) -> None:
    ids = _sequence(store, 2)
    _end(store, ids[0], "succeeded")
    frame_over(store.sessions, ids[0], Sent())
    _end(store, ids[1], "succeeded")

    def broker_down(name: str, args: list[Any], queue: str) -> str:
        raise ConnectionError("broker unreachable")

    with pytest.raises(ConnectionError):
        frame_over(store.sessions, ids[1], broker_down)
    with store.sessions() as session:
        parent = session.get(Job, PARENT)
        assert parent is not None and (parent.frames_done, parent.stage) == (1, "frames")
    sent = Sent()
    count_ended_frames(store.sessions, PARENT, sent)  # the sequence task, or a retry
    assert sent.calls == [("volumesh.sequence", [PARENT], "cpu")]
    count_ended_frames(store.sessions, PARENT, sent)
    assert len(sent.calls) == 1


def test_a_restart_sends_a_live_sequence_its_export_task(tmp_path: Path,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    from workers import recovery

    settings = Settings(data_dir=tmp_path)
    store = _store(settings)
    ids = _sequence(store, 2)
    sent: list[tuple[str, list[Any]]] = []

    class Celery:
        def send_task(self, name: str, args: list[Any], **_: Any) -> None:
            sent.append((name, args))

    monkeypatch.setattr(recovery, "make_celery", lambda _settings: Celery())
    assert set(recovery.requeue_unfinished(settings)) == {PARENT, *ids}
    assert ("volumesh.sequence", [PARENT]) in sent  # it does nothing until the frames are over
    assert all(("volumesh.stage", [i, 0]) in sent for i in ids)
