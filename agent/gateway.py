"""The gateway's stream routes over HTTP (docs/api.md, "Streams"), with the protocol's retry
rule: connection errors, 5xx, 408 and 429 are worth another try; other 4xx never are."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import httpx

API = "/api/v1"
FIRST_DELAY_S, MAX_DELAY_S = 0.2, 5.0


class RefusedError(Exception):
    """The gateway answered with a status not worth retrying."""

    def __init__(self, status: int, detail: str) -> None:
        super().__init__(f"{status} {detail}")
        self.status, self.detail = status, detail


class StoppedError(Exception):
    """Asked to stop while waiting for the gateway."""


def check_url(url: str) -> str:
    """The gateway's base URL without a trailing slash; ValueError unless http(s)://host."""
    try:
        parsed = httpx.URL(url)
    except (httpx.InvalidURL, TypeError):
        parsed = None
    if parsed is None or parsed.scheme not in ("http", "https") or not parsed.host:
        raise ValueError(f"--gateway: {url!r} is not an http(s):// URL of a gateway")
    return url.rstrip("/")


def retryable(status: int) -> bool:
    return status >= 500 or status in (408, 429)


def problem_detail(response: httpx.Response) -> str:
    """The problem+json's detail (or title), else the body's start."""
    try:
        body = response.json()
    except ValueError:
        return response.text[:200] or response.reason_phrase
    if isinstance(body, dict):
        return str(body.get("detail") or body.get("title") or body)[:500]
    return str(body)[:200]


class Backoff:
    """0.2 s, doubling to 5 s; back to 0.2 s after a success."""

    def __init__(self) -> None:
        self.delay_s = FIRST_DELAY_S

    def next(self) -> float:
        delay, self.delay_s = self.delay_s, min(self.delay_s * 2, MAX_DELAY_S)
        return delay

    def reset(self) -> None:
        self.delay_s = FIRST_DELAY_S


class Gateway:
    """A keep-alive client of one gateway with one API key, shared by the senders (httpx's
    Client is thread-safe); ``connections`` bounds the requests in flight."""

    def __init__(self, url: str, key: str, connections: int = 4, timeout_s: float = 30.0
                 ) -> None:
        self.url = check_url(url)
        limits = httpx.Limits(max_connections=connections, max_keepalive_connections=connections)
        self.client = httpx.Client(base_url=self.url + API, limits=limits,
                                   headers={"Authorization": f"Bearer {key}"},
                                   timeout=httpx.Timeout(timeout_s, connect=5.0))

    def close(self) -> None:
        self.client.close()

    def put_frame_set(self, stream_id: str, index: int, data: bytes, timestamp_us: int
                      ) -> httpx.Response:
        return self.client.put(f"/streams/{stream_id}/frames/{index}", content=data,
                               headers={"Content-Type": "application/zip",
                                        "Volumesh-Timestamp-Us": str(timestamp_us)})

    def call(self, method: str, path: str, stop: threading.Event,
             on_retry: Callable[[str], None] | None = None, deadline_s: float | None = None,
             **kwargs: Any) -> dict[str, Any]:
        """The answer's JSON; retried with backoff while worth it (until ``deadline_s``
        seconds of trying, when given). RefusedError for other 4xx; StoppedError on ``stop``;
        TimeoutError past the deadline."""
        backoff, waited_s = Backoff(), 0.0
        while True:
            try:
                response = self.client.request(method, path, **kwargs)
                if response.is_success:
                    return dict(response.json())
                if not retryable(response.status_code):
                    raise RefusedError(response.status_code, problem_detail(response))
                reason = f"{response.status_code} {problem_detail(response)}"
            except httpx.TransportError as exc:
                reason = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
            if on_retry is not None:
                on_retry(reason)
            delay = backoff.next()
            if deadline_s is not None and waited_s + delay > deadline_s:
                raise TimeoutError(reason)
            waited_s += delay
            if stop.wait(delay):
                raise StoppedError()
