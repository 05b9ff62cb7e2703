"""API keys: random, shown once, stored as SHA-256.

Keys carry 256 random bits, so a fast hash is enough: nobody can brute-force the preimage,
and a fast lookup keeps authenticated reads cheap.
"""

from __future__ import annotations

import hashlib
import secrets
from datetime import datetime

from sqlalchemy import select
from sqlalchemy.orm import Session

from workers.models import ApiKey, utcnow

KEY_PREFIX = "vmk_"


def hash_key(key: str) -> str:
    return hashlib.sha256(key.encode("utf-8", "surrogatepass")).hexdigest()


def create_key(session: Session, name: str) -> tuple[ApiKey, str]:
    """A new key named ``name``: the stored row and the key itself (shown only now)."""
    name = name.strip()
    if not name or len(name) > 100:
        raise ValueError("--name: a key needs a name of 1 to 100 characters")
    key = KEY_PREFIX + secrets.token_urlsafe(32)
    row = ApiKey(name=name, prefix=key[:12], key_hash=hash_key(key))
    session.add(row)
    session.commit()
    return row, key


def find_key(session: Session, key: str) -> ApiKey | None:
    """The live (not revoked) key row matching ``key``, or None."""
    row = session.scalar(select(ApiKey).where(ApiKey.key_hash == hash_key(key)))
    if row is None or row.revoked_at is not None:
        return None
    return row


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
