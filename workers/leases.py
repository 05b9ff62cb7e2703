"""Leases of running stages: a stage runs while one delivery of its task holds the job's lease.
Two beats renew it: a thread in the process running the stage (`Heartbeat`, which also notices
a lease lost to another delivery), and the worker's main process for the stages its pool
processes run (`renew_held_by`), which keeps a stage alive while native code in it holds the
GIL for long (open3d's Poisson solve does). A lease that lapsed (its worker was killed, ran out
of memory, or its machine is gone) is claimed by the gateway's sweep (`sweep_lapsed`), which
queues the stage again, or fails the job once the stage has lost its worker
``stage_max_tries`` times.

A claim is one conditional UPDATE on the lease as the sweeper saw it, so when several gateway
processes sweep, exactly one of them requeues a stage. A delivery of a stage whose lease
another delivery holds does not start (`JobStore.start_stage`), so a redelivered message of a
dead worker never runs beside the live holder; only a sweep turns a lapsed lease over.

Clocks: a lease's end is written by the worker's clock and read against the gateway's, so the
machines keep their clocks in sync (NTP) to well within ``stage_lease_s``.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import uuid
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from datetime import datetime, timedelta
from types import TracebackType
from typing import Any

from sqlalchemy import ColumnElement, CursorResult, or_, select, update
from sqlalchemy.orm import Session, sessionmaker

from workers.celery_app import TASK_STAGE, queue_for_stage
from workers.models import JOB_STATES, TERMINAL_STATES, Job, utcnow
from workers.sequence import frame_over
from workers.settings import Settings

log = logging.getLogger(__name__)

LIVE = tuple(s for s in JOB_STATES if s not in TERMINAL_STATES)
SendTask = Callable[[str, list[Any], str], str]
"""send(task name, args, queue) -> task id (`Gateway.send_task`)."""
UNSENT = "unsent"
"""Owner of a lease put back lapsed because its requeue could not be sent (the next sweep
tries again)."""
_MAX_SWEEP_INTERVAL_S = 5.0


def holder_prefix(pid: int) -> str:
    """How the owners of leases held by process ``pid`` of this machine begin."""
    return f"{socket.gethostname()[:80]}:{pid}:"


def new_owner() -> str:
    """A lease owner naming one delivery in this process (machine and pid let the worker's
    main process renew it; the random part makes it unique)."""
    return holder_prefix(os.getpid()) + uuid.uuid4().hex[:16]


def renew_interval_s(lease_s: float) -> float:
    """How often a holder renews: three beats per lease, so one late beat loses nothing."""
    return lease_s / 3


def sweep_interval_s(settings: Settings) -> float:
    """How often a gateway looks for lapsed leases."""
    return min(settings.stage_lease_s / 6, _MAX_SWEEP_INTERVAL_S)


def lease_free(index: int, owner: str) -> ColumnElement[bool]:
    """SQL: stage ``index`` may take the job's lease: none is held, ``owner`` holds it, or the
    holder ran an earlier stage (that queued this one and is ending)."""
    return or_(Job.lease_owner.is_(None), Job.lease_owner == owner, Job.stage_index < index)


def renew(sessions: sessionmaker[Session], job_id: str, owner: str, lease_s: float) -> bool:
    """Extend ``owner``'s lease by ``lease_s`` from now; False when it holds the lease no more
    (a sweep turned it over)."""
    with sessions.begin() as session:
        result: CursorResult[Any] = session.execute(  # type: ignore[assignment]
            update(Job).where(Job.id == job_id, Job.lease_owner == owner)
            .values(lease_expires_at=utcnow() + timedelta(seconds=lease_s)))
        return bool(result.rowcount)


def renew_held_by(sessions: sessionmaker[Session], pids: Iterable[int], lease_s: float) -> int:
    """Extend the leases held by the processes ``pids`` of this machine (a worker's pool
    processes now running a task); returns how many."""
    held = [Job.lease_owner.startswith(holder_prefix(pid), autoescape=True) for pid in pids]
    if not held:
        return 0
    with sessions.begin() as session:
        result: CursorResult[Any] = session.execute(  # type: ignore[assignment]
            update(Job).where(Job.state.in_(LIVE), or_(*held))
            .values(lease_expires_at=utcnow() + timedelta(seconds=lease_s)))
        return int(result.rowcount)


def release(sessions: sessionmaker[Session], job_id: str, owner: str) -> None:
    """Let go of ``owner``'s lease (a later holder's is left alone)."""
    with sessions.begin() as session:
        session.execute(update(Job).where(Job.id == job_id, Job.lease_owner == owner)
                        .values(lease_owner=None, lease_expires_at=None))


class Heartbeat:
    """Renews a lease from a daemon thread while a stage runs (stages can go long without a
    progress callback); released on exit. ``lost`` is set once the lease is someone else's."""

    def __init__(self, sessions: sessionmaker[Session], job_id: str, owner: str,
                 lease_s: float) -> None:
        self.sessions, self.job_id, self.owner, self.lease_s = sessions, job_id, owner, lease_s
        self.lost = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._beat, name=f"lease-{job_id[:8]}",
                                        daemon=True)

    def __enter__(self) -> Heartbeat:
        self._thread.start()
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        try:
            release(self.sessions, self.job_id, self.owner)
        except Exception:  # the lease lapses by itself; a sweep queues the stage again
            log.warning("job %s: could not release its lease", self.job_id, exc_info=True)

    def _beat(self) -> None:
        while not self._stop.wait(renew_interval_s(self.lease_s)):
            try:
                held = renew(self.sessions, self.job_id, self.owner, self.lease_s)
            except Exception:  # the store hiccuped: the next beat tries again
                log.warning("job %s: could not renew its lease", self.job_id, exc_info=True)
                continue
            if not held:
                self.lost.set()
                return


@dataclass(frozen=True)
class Lapsed:
    """A lapsed lease as a sweep saw it."""

    job_id: str
    owner: str
    stage_index: int
    stages: tuple[str, ...]
    lapses: int

    @property
    def stage(self) -> str:
        if 0 <= self.stage_index < len(self.stages):
            return self.stages[self.stage_index]
        return f"stage {self.stage_index}"


def lapsed_leases(sessions: sessionmaker[Session], now: datetime) -> list[Lapsed]:
    """Leases of queued or running jobs that ended before ``now``."""
    query = (select(Job.id, Job.lease_owner, Job.stage_index, Job.stages, Job.lease_lapses)
             .where(Job.state.in_(LIVE), Job.lease_owner.is_not(None),
                    Job.lease_expires_at < now))
    with sessions() as session:
        return [Lapsed(job_id, owner or "", index, tuple(stages or ()), lapses or 0)
                for job_id, owner, index, stages, lapses in session.execute(query)]


def give_up_message(stage: str, tries: int, max_tries: int) -> str:
    """Why a job failed: its stage kept losing its worker."""
    return (f"the {stage} stage's worker stopped answering {tries} times (killed, out of "
            f"memory or its machine lost); gave up, as VOLUMESH_STAGE_MAX_TRIES is {max_tries}")


def claim(sessions: sessionmaker[Session], lapsed: Lapsed, now: datetime,
          max_tries: int) -> str | None:
    """Take over a lapsed lease with one conditional UPDATE: "requeue" (the caller sends the
    stage's task), "failed" (its last try) or None (another sweep claimed it, or its holder
    renewed it after all)."""
    tries = lapsed.lapses + 1
    values: dict[str, Any] = {"lease_owner": None, "lease_expires_at": None,
                              "lease_lapses": tries, "updated_at": now}
    outcome = "failed" if tries >= max_tries else "requeue"
    if outcome == "failed":
        values.update(state="failed", finished_at=now,
                      error=give_up_message(lapsed.stage, tries, max_tries))
    else:
        values.update(state="queued")
    with sessions.begin() as session:
        result: CursorResult[Any] = session.execute(  # type: ignore[assignment]
            update(Job).where(Job.id == lapsed.job_id, Job.lease_owner == lapsed.owner,
                              Job.lease_expires_at < now, Job.state.in_(LIVE))
            .values(**values))
        return outcome if result.rowcount else None


def unclaim(sessions: sessionmaker[Session], lapsed: Lapsed, now: datetime) -> None:
    """Put a claimed lease back, lapsed, when its requeue could not be sent: the next sweep
    claims it again (counting the same lapse once)."""
    with sessions.begin() as session:
        session.execute(update(Job).where(Job.id == lapsed.job_id, Job.state == "queued",
                                          Job.lease_owner.is_(None))
                        .values(state="running", lease_owner=UNSENT, lease_expires_at=now,
                                lease_lapses=lapsed.lapses))


def sweep_lapsed(sessions: sessionmaker[Session], send: SendTask, settings: Settings,
                 now: datetime | None = None) -> dict[str, str]:
    """Claim every lapsed lease this sweep wins: requeue its stage, or fail the job after
    ``stage_max_tries``. Returns job id -> "requeue" | "failed" for the claims won."""
    now = now or utcnow()
    won: dict[str, str] = {}
    for lapsed in lapsed_leases(sessions, now):
        outcome = claim(sessions, lapsed, now, settings.stage_max_tries)
        if outcome is None:
            continue
        tries = lapsed.lapses + 1
        if outcome == "failed":
            log.warning("job %s failed: %s", lapsed.job_id,
                        give_up_message(lapsed.stage, tries, settings.stage_max_tries))
            frame_over(sessions, lapsed.job_id, send)  # a frame of a sequence: count it
        else:
            queue = queue_for_stage(lapsed.stage)
            try:
                send(TASK_STAGE, [lapsed.job_id, lapsed.stage_index], queue)
            except Exception:
                unclaim(sessions, lapsed, now)
                log.warning("job %s: could not queue %s again; the next sweep retries",
                            lapsed.job_id, lapsed.stage, exc_info=True)
                continue
            log.warning("job %s stage %d (%s): its worker stopped answering (lease lapsed); "
                        "queued again on %s, try %d of %d", lapsed.job_id, lapsed.stage_index,
                        lapsed.stage, queue, tries + 1, settings.stage_max_tries)
        won[lapsed.job_id] = outcome
    return won
