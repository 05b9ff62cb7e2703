"""Deleting what is older than ``VOLUMESH_RETENTION_DAYS``: finished jobs with their assets,
then captures that no job refers to any more.

A capture outlives its last job: it goes only once every job on it has finished longer ago
than the retention period (and been deleted), so a fresh asset never loses its capture. Rows
are deleted before their files: a crash in between leaves a file no row points to, never a
row pointing to nothing. Saved rigs are kept (they are small and outlive their captures).
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import delete, exists, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from workers.models import TERMINAL_STATES, Asset, Capture, Job
from workers.storage import ARTIFACTS, Storage

BATCH = 200
"""Most jobs (and captures) one pass deletes; the next pass takes the rest."""


@dataclass(frozen=True)
class Expired:
    jobs: int
    captures: int


def expire(sessions: sessionmaker[Session], storage: Storage, cutoff: datetime) -> Expired:
    """Delete finished jobs (and their assets) that finished before ``cutoff``, then captures
    made before it that no job refers to."""
    return Expired(jobs=_expire_jobs(sessions, storage, cutoff),
                   captures=_expire_captures(sessions, storage, cutoff))


def _expire_jobs(sessions: sessionmaker[Session], storage: Storage, cutoff: datetime) -> int:
    with sessions() as session:
        job_ids = list(session.scalars(
            select(Job.id).where(Job.state.in_(TERMINAL_STATES), Job.finished_at < cutoff)
            .limit(BATCH)))
    for job_id in job_ids:
        with sessions.begin() as session:
            files = session.scalar(select(Asset.files).where(Asset.job_id == job_id)) or {}
            session.execute(delete(Asset).where(Asset.job_id == job_id))
            session.execute(delete(Job).where(Job.id == job_id))
        for entry in files.values():
            with contextlib.suppress(FileNotFoundError):
                storage.delete(entry["key"])
    return len(job_ids)


def _expire_captures(sessions: sessionmaker[Session], storage: Storage,
                     cutoff: datetime) -> int:
    unused = ~exists().where(Job.capture_id == Capture.id)
    with sessions() as session:
        rows = list(session.execute(
            select(Capture.id, Capture.sha256, Capture.storage_key)
            .where(Capture.created_at < cutoff, Capture.state != "validating", unused)
            .limit(BATCH)))
    removed = 0
    for capture_id, sha256, storage_key in rows:
        try:
            with sessions.begin() as session:
                gone = session.execute(delete(Capture).where(Capture.id == capture_id, unused))
        except IntegrityError:  # a job on it was queued a moment ago: keep it
            continue
        if not gone.rowcount:  # type: ignore[attr-defined]
            continue
        with contextlib.suppress(FileNotFoundError):
            storage.delete(storage_key)
        storage.delete_prefix(f"{ARTIFACTS}/{sha256}/")
        removed += 1
    return removed
