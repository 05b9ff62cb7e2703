"""The agent's counters, shared by the capture loop and the senders, and the status line that
shows them."""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, replace

MB = 1_000_000
log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Snapshot:
    at_s: float
    """time.monotonic() of the snapshot."""
    captured: int = 0
    captured_bytes: int = 0
    sent: int = 0
    sent_bytes: int = 0
    dropped: int = 0
    """Live frame-sets not spooled: the spool was full."""
    rejected: int = 0
    previews_sent: int = 0
    previews_skipped: int = 0
    """Previews replaced by a newer one before they went, or not taken by the gateway."""
    spooled: int = 0
    spooled_bytes: int = 0
    connection: str = "connecting"


class Stats:
    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._now = Snapshot(at_s=0.0)

    def add(self, **counts: int) -> None:
        with self._lock:
            self._now = replace(self._now, **{k: getattr(self._now, k) + v
                                              for k, v in counts.items()})

    def set_connection(self, connection: str) -> None:
        """``connected`` or ``retrying (why)``; a change between the two is logged, so that
        a log shows when the gateway went away and came back."""
        with self._lock:
            was = self._now.connection
            self._now = replace(self._now, connection=connection)
        if connection == "connected" and was.startswith("retrying"):
            log.info("gateway back: sending the spool")
        elif connection.startswith("retrying") and not was.startswith("retrying"):
            log.info("gateway away, %s: capture goes on into the spool", connection)

    def snapshot(self, at_s: float, spooled: int, spooled_bytes: int) -> Snapshot:
        with self._lock:
            return replace(self._now, at_s=at_s, spooled=spooled, spooled_bytes=spooled_bytes)


def status_line(before: Snapshot, now: Snapshot) -> str:
    """``captured 120 (29.9/s, 12.2 MB/s)  sent 118 (29.5/s, 12.1 MB/s)  spool 2 (1.6 MB)
    gateway: connected`` (plus dropped and rejected counts when there are any)."""
    elapsed_s = max(now.at_s - before.at_s, 1e-6)

    def rate(a: int, b: int) -> float:
        return (b - a) / elapsed_s

    line = (f"captured {now.captured} ({rate(before.captured, now.captured):.1f}/s, "
            f"{rate(before.captured_bytes, now.captured_bytes) / MB:.1f} MB/s)  "
            f"sent {now.sent} ({rate(before.sent, now.sent):.1f}/s, "
            f"{rate(before.sent_bytes, now.sent_bytes) / MB:.1f} MB/s)  "
            f"spool {now.spooled} ({now.spooled_bytes / MB:.1f} MB)  gateway: {now.connection}")
    if now.dropped:
        line += f"  dropped {now.dropped}"
    if now.rejected:
        line += f"  rejected {now.rejected}"
    return line
