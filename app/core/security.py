"""API keys and who owns what.

Keys are random, shown once and stored as SHA-256: they carry 256 random bits, so a fast hash
is enough (nobody can brute-force the preimage), and a fast lookup keeps authenticated reads
cheap.

Every capture, job, asset and rig belongs to an *owner*: the project of the key that made it
(``project:NAME``), or the key itself when it has none (``key:ID``). A key sees only what its
owner owns; an admin key sees everything.
"""

from __future__ import annotations

import hashlib
import secrets
from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import Engine, bindparam, select
from sqlalchemy.orm import Session

from workers.models import ApiKey, CaptureGrant, utcnow

KEY_PREFIX = "vmk_"
_NAME_LIMIT = 100


@dataclass(frozen=True)
class Caller:
    """Who a request comes from: a live key, its owner, and whether it is an admin key."""

    key_id: str
    owner: str
    admin: bool

    def sees(self, owner: str | None) -> bool:
        """Whether something owned by ``owner`` is visible to this caller."""
        return self.admin or owner == self.owner


def owner_of(key_id: str, project: str | None) -> str:
    return f"project:{project}" if project else f"key:{key_id}"


def hash_key(key: str) -> str:
    return hashlib.sha256(key.encode("utf-8", "surrogatepass")).hexdigest()


def _checked_name(option: str, value: str) -> str:
    value = value.strip()
    if not value or len(value) > _NAME_LIMIT:
        raise ValueError(f"{option}: needs 1 to {_NAME_LIMIT} characters")
    return value


def create_key(session: Session, name: str, *, project: str | None = None,
               admin: bool = False) -> tuple[ApiKey, str]:
    """A new key named ``name``: the stored row and the key itself (shown only now)."""
    name = _checked_name("--name", name)
    if project is not None:
        project = _checked_name("--project", project)
    key = KEY_PREFIX + secrets.token_urlsafe(32)
    row = ApiKey(name=name, prefix=key[:12], key_hash=hash_key(key), project=project,
                 admin=admin)
    session.add(row)
    session.commit()
    return row, key


_LIVE_KEY = (select(ApiKey.__table__.c.id, ApiKey.__table__.c.project, ApiKey.__table__.c.admin)
             .where(ApiKey.__table__.c.key_hash == bindparam("key_hash"),
                    ApiKey.__table__.c.revoked_at.is_(None)))


def find_caller(engine: Engine, key: str) -> Caller | None:
    """The caller holding the live (not revoked) key ``key``, or None (one indexed read)."""
    with engine.connect() as conn:
        row = conn.execute(_LIVE_KEY, {"key_hash": hash_key(key)}).first()
    if row is None:
        return None
    return Caller(key_id=row.id, owner=owner_of(row.id, row.project), admin=bool(row.admin))


def revoke_key(session: Session, id_or_name: str) -> list[ApiKey]:
    """Revoke the key with this id, or every live key with this name; returns those revoked."""
    rows = list(session.scalars(select(ApiKey).where(
        (ApiKey.id == id_or_name) | (ApiKey.name == id_or_name))))
    now: datetime = utcnow()
    revoked = [row for row in rows if row.revoked_at is None]
    for row in revoked:
        row.revoked_at = now
    session.commit()
    return revoked


def list_keys(session: Session) -> list[ApiKey]:
    return list(session.scalars(select(ApiKey).order_by(ApiKey.created_at)))


def can_use_capture(session: Session, caller: Caller, capture_id: str) -> bool:
    """Whether the caller may see the capture and queue jobs on it (a grant of its owner)."""
    return caller.admin or session.get(CaptureGrant, (capture_id, caller.owner)) is not None
