"""Dropping captures that were never accepted: refused by their reader, or left `validating`
by a gateway that stopped while it waited for the verdict."""

from __future__ import annotations

import asyncio
import logging
from datetime import timedelta

from sqlalchemy import select

from app.core.context import Gateway
from workers.capture_registry import forget_capture
from workers.models import Capture, utcnow

log = logging.getLogger(__name__)


def forget(gateway: Gateway, capture_id: str, state: str = "rejected") -> bool:
    """Delete a capture still in ``state`` (rejected, or still validating): row and zip."""
    return forget_capture(gateway.sessions, gateway.storage, capture_id, state)


def forget_abandoned(gateway: Gateway) -> int:
    """Delete captures `validating` for twice the validation timeout: no upload waits for
    them any more (its gateway stopped), so nobody will learn their verdict."""
    cutoff = utcnow() - timedelta(seconds=2 * gateway.settings.validation_timeout_s)
    with gateway.sessions() as session:
        ids = list(session.scalars(select(Capture.id).where(Capture.state == "validating",
                                                            Capture.created_at < cutoff)))
    return sum(forget(gateway, capture_id, "validating") for capture_id in ids)


async def sweep_abandoned(gateway: Gateway) -> None:
    """`forget_abandoned` every validation timeout (first at start) until cancelled."""
    while True:
        try:
            removed = await asyncio.to_thread(forget_abandoned, gateway)
            if removed:
                log.info("removed %d captures left validating by a stopped gateway", removed)
        except Exception:  # the store hiccuped: the next sweep tries again
            log.warning("sweep of abandoned validations failed", exc_info=True)
        await asyncio.sleep(gateway.settings.validation_timeout_s)
