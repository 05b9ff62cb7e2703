"""The queues that live workers consume, as one gateway process sees them: read from the job
store (`workers.presence`) at most every ``cache_s``, so GET /jobs/{id}, the hottest route,
asks the store about workers only for a job that waits, and then rarely."""

from __future__ import annotations

import time

from sqlalchemy.orm import Session, sessionmaker

from workers.presence import live_queues

CACHE_S = 2.0


class LiveQueues:
    """A cached copy of the consumed queues (refreshed by the first caller after ``cache_s``;
    two callers refreshing at once is harmless)."""

    def __init__(self, sessions: sessionmaker[Session], heartbeat_s: float,
                 cache_s: float = CACHE_S) -> None:
        self.sessions, self.heartbeat_s, self.cache_s = sessions, heartbeat_s, cache_s
        self._queues: frozenset[str] = frozenset()
        self._read_at = -float("inf")

    def get(self) -> frozenset[str]:
        """The queues some live worker consumes."""
        now = time.monotonic()
        if now - self._read_at >= self.cache_s:
            self._queues = live_queues(self.sessions, self.heartbeat_s)
            self._read_at = now
        return self._queues
