"""The gateway's lease sweep: every few seconds, stages whose worker stopped renewing their
lease are queued again (or their job failed after too many tries) by `workers.leases`.
Every gateway process sweeps; each lapsed lease is claimed by exactly one of them."""

from __future__ import annotations

import asyncio
import logging

from app.core.context import Gateway
from workers.leases import sweep_interval_s, sweep_lapsed

log = logging.getLogger(__name__)


async def sweep_leases(gateway: Gateway) -> None:
    """Sweep lapsed leases every `sweep_interval_s` until cancelled."""
    interval_s = sweep_interval_s(gateway.settings)
    while True:
        await asyncio.sleep(interval_s)
        try:
            await asyncio.to_thread(sweep_lapsed, gateway.sessions, gateway.send_task,
                                    gateway.settings)
        except Exception:  # the store or broker hiccuped: the next sweep tries again
            log.warning("lease sweep failed; next in %.1f s", interval_s, exc_info=True)
