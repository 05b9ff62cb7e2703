"""The job store's conditional updates, on SQLite and on a fresh PostgreSQL database."""

from __future__ import annotations

from pathlib import Path

import pytest

from workers.db import init_db, make_engine, make_sessionmaker, normalise_url
from workers.jobstore import JobStore
from workers.models import Capture, Job
from workers.settings import Settings


@pytest.fixture
def store(store_settings: Settings) -> JobStore:
    return _store(store_settings)


def _store(settings: Settings) -> JobStore:
    engine = make_engine(settings)
    init_db(engine)
    init_db(engine)  # idempotent
    store = JobStore(make_sessionmaker(engine))
    with store.sessions.begin() as session:
        session.add(Capture(id="c" * 32, sha256="c" * 64, size_bytes=1, storage_key="k",
                            state="validating"))
        session.add(Job(id="j" * 32, capture_id="c" * 32, options={"enhance": False},
                        stages=[], stage_timings={}))
    return store


def test_postgres_urls_use_psycopg3() -> None:
    assert normalise_url("postgresql://u@h/db") == "postgresql+psycopg://u@h/db"
    assert normalise_url("postgres://u@h/db") == "postgresql+psycopg://u@h/db"
    assert normalise_url("sqlite:///x.db") == "sqlite:///x.db"


def test_a_stage_runs_once_and_advances_once(store: JobStore) -> None:
    job_id = "j" * 32
    assert store.set_plan(job_id, ["a", "b", "export"]) == ("a", "b", "export")
    assert store.set_plan(job_id, ["other"]) == ("a", "b", "export")  # the first plan holds
    assert store.start_stage(job_id, 0, "a", "t0")
    with store.sessions() as session:
        first = session.get(Job, job_id)
        assert first is not None and first.started_at is not None
        started = first.started_at
    assert store.progress(job_id, 0.2) == "running"
    assert store.finish_stage(job_id, 0, "a", 1.5, 1 / 3)
    assert not store.finish_stage(job_id, 0, "a", 1.5, 1 / 3)  # a duplicate does not advance
    assert not store.start_stage(job_id, 0, "a", "t0-again")  # nor start again
    assert store.start_stage(job_id, 1, "b", "t1")
    view = store.load(job_id)
    assert view is not None and view.done_count == 1 and view.stages == ("a", "b", "export")
    assert store.succeed(job_id, job_id, {"mesh.glb": {"key": "k", "sha256": "s", "bytes": 1,
                                                        "content_type": "x"}}, 0.5)
    assert not store.succeed(job_id, job_id, {}, 0.5)
    with store.sessions() as session:
        job = session.get(Job, job_id)
        assert job is not None
        assert (job.state, job.progress, job.asset_id) == ("succeeded", 1.0, job_id)
        assert job.stage_timings == {"a": 1.5, "export": 0.5}
        assert job.finished_at is not None and job.started_at == started


def test_cancelled_job_takes_no_more_work(store: JobStore) -> None:
    job_id = "j" * 32
    store.set_plan(job_id, ["a", "export"])
    assert store.start_stage(job_id, 0, "a", "t0")
    with store.sessions.begin() as session:
        job = session.get(Job, job_id)
        assert job is not None
        job.state = "cancelled"
    assert store.progress(job_id, 0.5) == "cancelled"
    assert not store.finish_stage(job_id, 0, "a", 1.0, 0.5)
    assert not store.start_stage(job_id, 1, "export", "t1")
    store.fail(job_id, "too late")
    assert store.state(job_id) == "cancelled"


def test_failure_is_recorded_once(store: JobStore) -> None:
    job_id = "j" * 32
    store.fail(job_id, "capture.json: cameras[0].fx: must be positive")
    store.fail(job_id, "second failure")
    with store.sessions() as session:
        job = session.get(Job, job_id)
        assert job is not None and job.state == "failed"
        assert job.error == "capture.json: cameras[0].fx: must be positive"


def test_capture_validation_results(store: JobStore) -> None:
    capture_id = "c" * 32
    assert store.capture(capture_id) == ("c" * 64, "k")
    store.capture_validated(capture_id, 8, (0, 1))
    store.capture_rejected(capture_id, "late verdict")  # a ready capture stays ready
    with store.sessions() as session:
        row = session.get(Capture, capture_id)
        assert row is not None and (row.state, row.cameras, row.frames) == ("ready", 8, 2)
    assert store.capture("f" * 32) is None


def test_columns_added_to_an_older_store(tmp_path: Path) -> None:
    import sqlite3

    db = tmp_path / "volumesh.db"
    settings = Settings(data_dir=tmp_path)
    init_db(make_engine(settings))
    with sqlite3.connect(db) as conn:  # a store written before jobs had started_at
        conn.execute("ALTER TABLE jobs DROP COLUMN started_at")
    init_db(make_engine(settings))
    with sqlite3.connect(db) as conn:
        columns = {row[1] for row in conn.execute("PRAGMA table_info(jobs)")}
    assert "started_at" in columns
