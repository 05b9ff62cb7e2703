"""Which workers are alive and which queues they consume, as the workers themselves record it.

A worker's main process (not its pool's) writes a row in the ``workers`` table once it is ready
and renews ``last_seen`` every ``worker_heartbeat_s`` from a daemon thread; a clean stop deletes
the row, a killed worker's row goes stale. The same thread renews the leases of the stages its
pool processes run (`workers.leases.renew_held_by`). The gateway reads the queues of the fresh
rows to tell a queued job why it waits and to answer /readyz. Nothing here asks the workers
through the broker: the embedded file-system broker has no broadcast.
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Callable, Iterable
from datetime import UTC, datetime, timedelta
from typing import Any

from sqlalchemy import CursorResult, delete, select, update
from sqlalchemy.orm import Session, sessionmaker

from workers.celery_app import QUEUE_CPU, TASK_STAGE, queue_for_stage
from workers.db import init_db, make_engine, make_sessionmaker
from workers.leases import LIVE, renew_held_by
from workers.models import WorkerSeen, new_id, utcnow
from workers.settings import Settings, get_settings

log = logging.getLogger(__name__)

STALE_BEATS = 3
"""A worker silent for this many heartbeats counts as gone."""
FORGET_AFTER_S = 3600.0
"""Rows of workers silent this long are deleted (a killed worker never deletes its own)."""


def _aware(value: datetime) -> datetime:
    # SQLite hands back naive datetimes; they were written in UTC.
    return value if value.tzinfo is not None else value.replace(tzinfo=UTC)


def announce(sessions: sessionmaker[Session], worker_id: str, hostname: str, pid: int,
             queues: list[str], now: datetime | None = None) -> None:
    """Record that the worker is alive now and consumes ``queues``."""
    now = now or utcnow()
    with sessions.begin() as session:
        result: CursorResult[Any] = session.execute(  # type: ignore[assignment]
            update(WorkerSeen).where(WorkerSeen.id == worker_id)
            .values(last_seen=now, queues=queues))
        if not result.rowcount:  # first beat, or the row was forgotten while this one stalled
            session.add(WorkerSeen(id=worker_id, hostname=hostname, pid=pid, queues=queues,
                                   started_at=now, last_seen=now))
        session.execute(delete(WorkerSeen).where(
            WorkerSeen.last_seen < now - timedelta(seconds=FORGET_AFTER_S)))


def retire(sessions: sessionmaker[Session], worker_id: str) -> None:
    """Delete the worker's row (it stops cleanly)."""
    with sessions.begin() as session:
        session.execute(delete(WorkerSeen).where(WorkerSeen.id == worker_id))


def live_workers(sessions: sessionmaker[Session], heartbeat_s: float,
                 now: datetime | None = None) -> list[WorkerSeen]:
    """Workers heard from within the last ``STALE_BEATS`` heartbeats."""
    since = (now or utcnow()) - timedelta(seconds=STALE_BEATS * heartbeat_s)
    with sessions() as session:
        return list(session.scalars(select(WorkerSeen).where(WorkerSeen.last_seen >= since)))


def live_queues(sessions: sessionmaker[Session], heartbeat_s: float,
                now: datetime | None = None) -> frozenset[str]:
    """The queues that live workers consume."""
    return frozenset(q for w in live_workers(sessions, heartbeat_s, now) for q in w.queues or ())


def waiting_queue(job: Any, now: datetime | None = None) -> str | None:
    """The queue a live job waits on for its next stage; None while a stage of it runs under
    a live lease, or once it has ended. ``job``: a jobs row (ORM or Core)."""
    if job.state not in LIVE:
        return None
    if job.lease_owner is not None and job.lease_expires_at is not None and \
            _aware(job.lease_expires_at) > (now or utcnow()):
        return None
    stages = job.stages or ()
    if job.done_count < len(stages):
        return queue_for_stage(stages[job.done_count])
    return QUEUE_CPU  # not planned yet: every job starts on the cpu queue


def waiting_reason(job: Any, consumed: Callable[[], frozenset[str]],
                   now: datetime | None = None) -> str | None:
    """Why the job waits, when no live worker consumes the queue it waits on; else None.
    ``consumed`` is called only for a job that waits (the gateway caches it)."""
    queue = waiting_queue(job, now)
    if queue is None or queue in consumed():
        return None
    return no_worker_message(queue)


def no_worker_message(queue: str) -> str:
    return f"no worker consumes the '{queue}' queue; start one with `volumesh worker --queues " \
           f"{queue}`"


class Announcer:
    """The thread that keeps a worker's row fresh and renews the leases of the stages its pool
    processes ``busy_pids()`` run (started once the worker is ready)."""

    def __init__(self, settings: Settings, hostname: str, queues: list[str],
                 busy_pids: Callable[[], Iterable[int]] = tuple) -> None:
        self.engine = make_engine(settings)
        self.sessions = make_sessionmaker(self.engine)
        self.heartbeat_s = settings.worker_heartbeat_s
        self.lease_s = settings.stage_lease_s
        self.busy_pids = busy_pids
        self.worker_id, self.hostname, self.pid = new_id(), hostname, os.getpid()
        self.queues = sorted(queues)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._beat, name="presence", daemon=True)

    def start(self) -> None:
        """Record the worker now (so it counts from its "ready" on), then every beat."""
        try:
            init_db(self.engine)  # a worker may start before any gateway made the table
            announce(self.sessions, self.worker_id, self.hostname, self.pid, self.queues)
        except Exception:  # a worker that cannot record itself still works; the beat retries
            log.warning("could not record this worker in the job store", exc_info=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        try:
            retire(self.sessions, self.worker_id)
        finally:
            self.engine.dispose()

    def _beat(self) -> None:
        interval_s = min(self.heartbeat_s, self.lease_s / 3)
        while not self._stop.wait(interval_s):
            try:
                announce(self.sessions, self.worker_id, self.hostname, self.pid, self.queues)
                renew_held_by(self.sessions, self.busy_pids(), self.lease_s)
            except Exception:  # the store hiccuped: the next beat tries again
                log.warning("could not record this worker as alive", exc_info=True)


_announcer: Announcer | None = None


def _busy_pool_pids() -> set[int]:
    """Pool processes of this worker now running a stage task (Celery's own record)."""
    from celery.worker import state

    try:
        requests = tuple(state.active_requests)
    except RuntimeError:  # changed while read: the next beat reads it again
        return set()
    return {r.worker_pid for r in requests if r.worker_pid and r.name == TASK_STAGE}


def start_announcing(consumer: Any) -> None:
    """``worker_ready`` handler: record the worker (its Celery consumer) and keep it fresh."""
    global _announcer
    settings: Settings = getattr(consumer.app, "volumesh_settings", None) or get_settings()
    queues = list(consumer.app.amqp.queues.consume_from)
    _announcer = Announcer(settings, str(consumer.hostname), queues, _busy_pool_pids)
    _announcer.start()
    log.info("worker %s consumes %s", consumer.hostname, ", ".join(_announcer.queues))


def stop_announcing() -> None:
    """``worker_shutdown`` handler: delete the worker's row."""
    global _announcer
    if _announcer is not None:
        announcer, _announcer = _announcer, None
        try:
            announcer.stop()
        except Exception:
            log.warning("could not delete this worker's row", exc_info=True)
