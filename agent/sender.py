"""Senders: threads that PUT the oldest spooled frame-sets to the gateway, a few at a time.

Each takes the oldest frame-set no other sender holds and keeps at it until the gateway
answers for it: 200/201 acknowledge it (deleted from the spool), another 4xx refuses it
(moved to rejected/, one log line), and connection errors, 5xx, 408 and 429 are retried
with backoff (0.2 s doubling to 5 s). While the gateway is away the capture goes on into
the spool; when it is back, the backlog goes in index order.
"""

from __future__ import annotations

import logging
import threading

import httpx

from agent.gateway import Backoff, Gateway, problem_detail, retryable
from agent.spool import Spool, SpooledFrameSet
from agent.stats import Stats

log = logging.getLogger(__name__)


class Senders:
    def __init__(self, gateway: Gateway, stream_id: str, spool: Spool, stats: Stats,
                 count: int, stop: threading.Event) -> None:
        self.gateway, self.stream_id, self.spool, self.stats = gateway, stream_id, spool, stats
        self.stop = stop
        # Daemons: a sender mid-request must not hold up an interrupted agent's exit; the
        # frame-set it holds stays in the spool for the next run.
        self.threads = [threading.Thread(target=self._run, name=f"sender-{i}", daemon=True)
                        for i in range(count)]

    def start(self) -> None:
        for thread in self.threads:
            thread.start()

    def _run(self) -> None:
        while not (self.stop.is_set() or self.spool.closed):
            entry = self.spool.take(timeout_s=0.5)
            if entry is not None:
                self._deliver(entry)

    def _deliver(self, entry: SpooledFrameSet) -> None:
        backoff = Backoff()
        while not self.stop.is_set():
            response = self._attempt(entry)
            if response is not None and self._answered(entry, response):
                return
            self.stop.wait(_delay_s(backoff, response))

    def _attempt(self, entry: SpooledFrameSet) -> httpx.Response | None:
        """The gateway's answer; None when it could not be reached."""
        try:
            return self.gateway.put_frame_set(self.stream_id, entry.index,
                                              entry.path.read_bytes(), entry.timestamp_us)
        except httpx.TransportError as exc:
            self.stats.set_connection(f"retrying ({type(exc).__name__})")
            return None

    def _answered(self, entry: SpooledFrameSet, response: httpx.Response) -> bool:
        """True when the gateway settled the frame-set (acknowledged or refused)."""
        status = response.status_code
        if status in (200, 201):
            self.spool.acknowledge(entry)
            self.stats.add(sent=1, sent_bytes=entry.size_bytes)
            self.stats.set_connection("connected")
            return True
        if retryable(status):
            self.stats.set_connection(f"retrying ({status})")
            return False
        target = self.spool.reject(entry)
        self.stats.add(rejected=1)
        self.stats.set_connection("connected")
        log.warning("frame-set %d refused (%d %s): moved to %s", entry.index, status,
                    problem_detail(response), target)
        return True


def _delay_s(backoff: Backoff, response: httpx.Response | None) -> float:
    """The backoff's next delay, or longer where a 429/503 says Retry-After (seconds)."""
    delay = backoff.next()
    retry_after = response.headers.get("Retry-After") if response is not None else None
    if retry_after is not None and retry_after.isdigit():
        delay = max(delay, min(float(retry_after), 60.0))
    return delay
