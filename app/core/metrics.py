"""Prometheus metrics of one gateway process: requests by route and status, and job counts."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from typing import Any

from prometheus_client import CollectorRegistry, Counter, Histogram
from prometheus_client.core import GaugeMetricFamily
from prometheus_client.registry import Collector
from sqlalchemy import func, select
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app.schemas import API_PREFIX
from workers.models import JOB_STATES, Job

UPLOAD_BYTES_KEY = "upload_bytes"
"""Request-state name under which a received upload leaves its size for the counter."""


class Metrics:
    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        self.requests = Counter("volumesh_http_requests", "HTTP requests answered",
                                ["method", "route", "status"], registry=self.registry)
        self.latency = Histogram("volumesh_http_request_seconds", "Time to answer a request",
                                 ["method", "route"], registry=self.registry,
                                 buckets=(.001, .0025, .005, .01, .025, .05, .1, .25, .5, 1,
                                          2.5, 5, 10, 30))
        self.upload_bytes = Counter("volumesh_upload_bytes",
                                    "Bytes of capture zips received in accepted uploads",
                                    registry=self.registry)

    def watch_jobs(self, sessions: Callable[[], Any]) -> None:
        self.registry.register(_JobCollector(sessions))


class _JobCollector(Collector):
    """Jobs per state, read from the job store at scrape time (true across all gateways)."""

    def __init__(self, sessions: Callable[[], Any]) -> None:
        self.sessions = sessions

    def collect(self) -> Iterator[GaugeMetricFamily]:
        family = GaugeMetricFamily("volumesh_jobs", "Jobs in the store by state",
                                   labels=["state"])
        try:
            with self.sessions() as session:
                counts = dict(session.execute(select(Job.state, func.count()).group_by(Job.state))
                              .all())
        except Exception:  # a scrape must not fail because the store is down
            return
        for state in JOB_STATES:
            family.add_metric([state], counts.get(state, 0))
        yield family


def _route_name(scope: Scope) -> str:
    # The matched route's template (/api/v1/jobs/{job_id}), not the path, keeps the number of
    # label values bounded; the router leaves the route in the scope (its path is relative to
    # the /api/v1 router it was included by).
    route = scope.get("route")
    path = str(getattr(route, "path", "") or "")
    if not path:
        return "unmatched"
    if scope["path"].startswith(API_PREFIX + "/") and not path.startswith(API_PREFIX):
        return API_PREFIX + path
    return path


class MetricsMiddleware:
    def __init__(self, app: ASGIApp, metrics: Metrics) -> None:
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = time.perf_counter()
        status = 500

        async def send_status(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        # The request's state dict is shared with every Request made from this scope, so the
        # upload's size set deep in the route is read here once the answer is known.
        state = scope.setdefault("state", {})
        try:
            await self.app(scope, receive, send_status)
        finally:
            route = _route_name(scope)
            method = scope.get("method", "")
            self.metrics.requests.labels(method, route, str(status)).inc()
            self.metrics.latency.labels(method, route).observe(time.perf_counter() - started)
            uploaded = state.get(UPLOAD_BYTES_KEY)
            if uploaded and 200 <= status < 300:
                self.metrics.upload_bytes.inc(uploaded)
