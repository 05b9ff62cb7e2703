"""Storing a capture zip: once per content (id = the start of its SHA-256), granted to each
owner that brings it. Shared by the gateway's upload and a worker's stream assembly."""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from sqlalchemy import delete, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from workers.models import Capture, CaptureGrant, new_id, utcnow
from workers.storage import Storage


@dataclass(frozen=True)
class CaptureZip:
    """A complete capture zip on local disk, hashed."""

    path: Path
    sha256: str
    size_bytes: int


@dataclass(frozen=True)
class Registered:
    capture_id: str
    needs_validation: bool
    """True when nobody is reading the capture yet (stored now, or left `validating` by a
    reader that gave up)."""
    had_it: bool
    """The owner could use the capture already (it brought the same bytes before)."""


def register_capture(sessions: sessionmaker[Session], storage: Storage, zipped: CaptureZip,
                     owner: str, stale_after_s: float) -> Registered:
    """Store the zip once per content and grant it to ``owner``; ``zipped.path`` may be
    consumed. A capture `validating` for over ``stale_after_s`` needs validating again."""
    capture_id = zipped.sha256[:32]
    with sessions() as session:
        existing = session.get(Capture, capture_id)
        if existing is not None and existing.state != "rejected":
            stale = (existing.state == "validating" and (utcnow() - _aware(existing.created_at))
                     .total_seconds() > stale_after_s)
            return Registered(capture_id, stale, not grant_capture(session, capture_id, owner))
    if existing is not None:  # rejected by an earlier reader: read it again
        forget_capture(sessions, storage, capture_id)
    # A key of this zip's own: deleting a refused upload's zip can never take the zip of the
    # same bytes uploaded again a moment later.
    key = f"captures/{zipped.sha256}-{new_id()[:8]}.zip"
    storage.put_file(key, zipped.path, move=True)
    with sessions() as session:
        session.add(Capture(id=capture_id, sha256=zipped.sha256, size_bytes=zipped.size_bytes,
                            storage_key=key, state="validating"))
        try:
            session.commit()
        except IntegrityError:  # the same content arrived twice at once: the other one won
            session.rollback()
            storage.delete(key)
            return Registered(capture_id, False, not grant_capture(session, capture_id, owner))
        grant_capture(session, capture_id, owner)
    return Registered(capture_id, True, False)


def grant_capture(session: Session, capture_id: str, owner: str) -> bool:
    """Let ``owner`` use the capture; False when it could already."""
    if session.get(CaptureGrant, (capture_id, owner)) is not None:
        return False
    session.add(CaptureGrant(capture_id=capture_id, owner=owner))
    try:
        session.commit()
    except IntegrityError:  # the same owner brought it twice at once
        session.rollback()
        return False
    return True


def forget_capture(sessions: sessionmaker[Session], storage: Storage, capture_id: str,
                   state: str = "rejected") -> bool:
    """Delete a capture still in ``state`` (rejected, or still validating): row and zip.

    One conditional DELETE, so a capture a worker has just marked ready is never taken."""
    with sessions() as session:
        key = session.scalar(select(Capture.storage_key).where(Capture.id == capture_id))
        deleted = session.execute(delete(Capture).where(Capture.id == capture_id,
                                                        Capture.state == state))
        session.commit()
    if key is None or not deleted.rowcount:  # type: ignore[attr-defined]
        return False
    with contextlib.suppress(FileNotFoundError):
        storage.delete(key)
    return True


def _aware(value: datetime) -> datetime:
    # SQLite hands back naive datetimes; they were written in UTC.
    return value.replace(tzinfo=UTC) if value.tzinfo is None else value
