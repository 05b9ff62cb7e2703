"""What one gateway process holds: settings, job store, storage and a task sender."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

from celery import Celery
from sqlalchemy import Engine
from sqlalchemy.orm import Session, sessionmaker

from app.core.metrics import Metrics
from app.core.queues import LiveQueues
from app.core.sharing import load_secret
from workers.celery_app import make_celery
from workers.db import init_db, make_engine, make_sessionmaker
from workers.settings import Settings
from workers.storage import Storage, make_storage

log = logging.getLogger(__name__)

_PUBLISH_RETRY = {"max_retries": 3, "interval_start": 0.1, "interval_step": 0.3,
                  "interval_max": 0.5}


@dataclass
class Gateway:
    settings: Settings
    engine: Engine
    sessions: sessionmaker[Session]
    storage: Storage
    celery: Celery
    metrics: Metrics
    share_secret: bytes = b""
    """Signs asset share links (`app.core.sharing`); read from the job store on start."""
    queues: LiveQueues = field(init=False)
    """The queues live workers consume (cached; a job waiting on another says so)."""

    def __post_init__(self) -> None:
        self.queues = LiveQueues(self.sessions, self.settings.worker_heartbeat_s)

    @classmethod
    def create(cls, settings: Settings) -> Gateway:
        engine = make_engine(settings)
        return cls(settings=settings, engine=engine, sessions=make_sessionmaker(engine),
                   storage=make_storage(settings), celery=make_celery(settings),
                   metrics=Metrics())

    def start(self) -> None:
        init_db(self.engine)
        self.share_secret = load_secret(self.sessions)
        self.metrics.watch_jobs(self.sessions)

    def close(self) -> None:
        self.engine.dispose()

    def send_task(self, name: str, args: list[Any], queue: str) -> str:
        """Queue a task by name (the gateway never imports task code); returns its id.

        Retries briefly (a request is waiting), then raises kombu's ``OperationalError``,
        which the app answers with 503.
        """
        result = self.celery.send_task(name, args=args, queue=queue, routing_key=queue,
                                       retry=True, retry_policy=_PUBLISH_RETRY)
        return str(result.id)

    def send_group(self, name: str, args_list: list[list[Any]], queue: str) -> list[str]:
        """Queue one task per argument list at once (a Celery group; no result backend is
        needed, as the job store tracks completion); returns their ids in order."""
        from celery import group

        signatures = [self.celery.signature(name, args=args, queue=queue, routing_key=queue)
                      for args in args_list]
        result = group(signatures).apply_async(retry=True, retry_policy=_PUBLISH_RETRY)
        return [str(child.id) for child in result.results]

    def revoke(self, task_id: str) -> None:
        """Drop a queued task (best effort: workers also check the job state)."""
        if self.settings.embedded:
            return  # the embedded broker has no broadcast; the state check suffices
        try:
            self.celery.control.revoke(task_id)
        except Exception:  # a revoke is an optimisation; never fail a cancel over it
            log.warning("could not broadcast revoke of %s", task_id, exc_info=True)

    def ping_broker(self, timeout_s: float = 2.0) -> None:
        with self.celery.connection_for_write() as conn:
            conn.ensure_connection(max_retries=1, timeout=timeout_s)
