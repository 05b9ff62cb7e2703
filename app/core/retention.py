"""The gateway's retention sweep: hourly, what is older than ``VOLUMESH_RETENTION_DAYS`` is
deleted by `workers.retention` (nothing, when the setting is unset)."""

from __future__ import annotations

import asyncio
import logging
from datetime import timedelta

from app.core.context import Gateway
from workers.models import utcnow
from workers.retention import expire

log = logging.getLogger(__name__)

INTERVAL_S = 3600.0


async def sweep_retention(gateway: Gateway) -> None:
    """Expire old jobs, assets and captures every `INTERVAL_S` (first at start) until
    cancelled."""
    days = gateway.settings.retention_days
    if days is None:
        return
    while True:
        try:
            expired = await asyncio.to_thread(expire, gateway.sessions, gateway.storage,
                                              utcnow() - timedelta(days=days))
            if expired.jobs or expired.captures:
                log.info("retention: deleted %d jobs and %d captures older than %g days",
                         expired.jobs, expired.captures, days)
        except Exception:  # the store hiccuped: the next sweep tries again
            log.warning("retention sweep failed", exc_info=True)
        await asyncio.sleep(INTERVAL_S)
