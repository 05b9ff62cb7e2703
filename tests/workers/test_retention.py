"""Retention: old finished jobs go with their asset files, captures go after their last job,
and nothing young or live is touched."""

from __future__ import annotations

from datetime import timedelta
from pathlib import Path

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from workers.db import init_db, make_engine, make_sessionmaker
from workers.models import Asset, Capture, CaptureGrant, Job, utcnow
from workers.retention import expire
from workers.settings import Settings
from workers.storage import LocalStorage, Storage

DAY = timedelta(days=1)


def _capture(sessions: sessionmaker[Session], storage: Storage, tag: str, age: timedelta
             ) -> str:
    sha = tag * 64
    storage.put_bytes(f"captures/{sha}.zip", b"zip")
    storage.put_bytes(f"artifacts/{sha}/0-filter.npz", b"npz")
    with sessions.begin() as session:
        session.add(Capture(id=sha[:32], sha256=sha, size_bytes=3, state="ready",
                            storage_key=f"captures/{sha}.zip", created_at=utcnow() - age))
        session.flush()
        session.add(CaptureGrant(capture_id=sha[:32], owner="key:x"))
    return sha[:32]


def _job(sessions: sessionmaker[Session], storage: Storage, capture_id: str, job_id: str,
         state: str, finished_ago: timedelta | None) -> None:
    finished = None if finished_ago is None else utcnow() - finished_ago
    key = f"assets/{job_id}/mesh.glb"
    storage.put_bytes(key, b"glb")
    with sessions.begin() as session:
        session.add(Job(id=job_id, capture_id=capture_id, state=state, finished_at=finished))
        session.flush()
        session.add(Asset(id=job_id, job_id=job_id, files={"mesh.glb": {"key": key}}))


def test_expiry_keeps_what_is_young_or_live(tmp_path: Path) -> None:
    engine = make_engine(Settings(data_dir=tmp_path))
    init_db(engine)
    sessions = make_sessionmaker(engine)
    storage = LocalStorage(tmp_path / "storage")
    old = _capture(sessions, storage, "a", 40 * DAY)  # its only job finished long ago
    reused = _capture(sessions, storage, "b", 40 * DAY)  # an old capture with a recent job
    busy = _capture(sessions, storage, "c", 40 * DAY)  # an old capture with a running job
    young = _capture(sessions, storage, "d", 1 * DAY)
    _job(sessions, storage, old, "1" * 32, "succeeded", 35 * DAY)
    _job(sessions, storage, reused, "2" * 32, "succeeded", 35 * DAY)
    _job(sessions, storage, reused, "3" * 32, "failed", 2 * DAY)
    _job(sessions, storage, busy, "4" * 32, "running", None)
    _job(sessions, storage, young, "5" * 32, "succeeded", 1 * DAY)

    expired = expire(sessions, storage, utcnow() - 30 * DAY)

    assert (expired.jobs, expired.captures) == (2, 1)
    with sessions() as session:
        assert set(session.scalars(select(Job.id))) == {"3" * 32, "4" * 32, "5" * 32}
        assert set(session.scalars(select(Asset.id))) == {"3" * 32, "4" * 32, "5" * 32}
        assert set(session.scalars(select(Capture.id))) == {reused, busy, young}
        assert old not in set(session.scalars(select(CaptureGrant.capture_id)))
    assert not storage.exists(f"captures/{'a' * 64}.zip")
    assert not storage.exists(f"artifacts/{'a' * 64}/0-filter.npz")
    assert not storage.exists(f"assets/{'1' * 32}/mesh.glb")
    assert not storage.exists(f"assets/{'2' * 32}/mesh.glb")
    for kept in (f"captures/{'b' * 64}.zip", f"assets/{'3' * 32}/mesh.glb",
                 f"assets/{'4' * 32}/mesh.glb", f"captures/{'d' * 64}.zip"):
        assert storage.exists(kept), kept
    # Once its last job has expired too, the reused capture goes.
    later = expire(sessions, storage, utcnow() + 1 * DAY)
    assert later.captures >= 1
    with sessions() as session:
        assert reused not in set(session.scalars(select(Capture.id)))
        assert busy in set(session.scalars(select(Capture.id)))
