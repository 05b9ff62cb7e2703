"""Share links: a signed token that lets anyone holding it read one asset until it expires
(a sequence's asset: the sequence and the assets of its frames, which its manifest links).

The token is ``EXPIRES.SIGNATURE``: the expiry as a Unix time and an HMAC-SHA256 over the asset
id and that expiry, keyed by a random secret that every gateway reads from the job store (so a
link made by one gateway process is honoured by all of them).
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import secrets

from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from workers.models import ServiceSecret

SECRET_NAME = "share-links"


def load_secret(sessions: sessionmaker[Session]) -> bytes:
    """The share-link secret, made on the first start of the first gateway."""
    with sessions() as session:
        row = session.get(ServiceSecret, SECRET_NAME)
        if row is None:
            session.add(ServiceSecret(name=SECRET_NAME, value=secrets.token_hex(32)))
            try:
                session.commit()
            except IntegrityError:  # another gateway made it a moment ago
                session.rollback()
            row = session.get(ServiceSecret, SECRET_NAME)
        assert row is not None
        return bytes.fromhex(row.value)


def _signature(secret: bytes, asset_id: str, expires_unix_s: int) -> str:
    digest = hmac.new(secret, f"asset:{asset_id}:{expires_unix_s}".encode(), hashlib.sha256)
    return base64.urlsafe_b64encode(digest.digest()).rstrip(b"=").decode()


def share_token(secret: bytes, asset_id: str, expires_unix_s: int) -> str:
    return f"{expires_unix_s}.{_signature(secret, asset_id, expires_unix_s)}"


def token_grants(secret: bytes, asset_id: str, token: str, now_unix_s: float) -> bool:
    """Whether ``token`` is a share link of this asset that has not expired."""
    expires_text, _, signature = token.partition(".")
    if not expires_text.isdigit() or len(expires_text) > 12:
        return False
    expires_unix_s = int(expires_text)
    expected = _signature(secret, asset_id, expires_unix_s)
    return hmac.compare_digest(signature, expected) and now_unix_s < expires_unix_s


def token_grants_any(secret: bytes, asset_ids: list[str], token: str, now_unix_s: float) -> bool:
    """Whether ``token`` is a live share link of one of these assets (an asset, then the
    sequence it is a frame of)."""
    return any(token_grants(secret, asset_id, token, now_unix_s) for asset_id in asset_ids)
