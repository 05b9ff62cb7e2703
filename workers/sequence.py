"""Sequence jobs: every frame of a capture reconstructed in parallel, then one manifest.

A sequence job (``frames_total`` set) owns one frame job per capture frame (``parent_id`` =
its id, ``frame_index`` the frame): each is an ordinary chain of stage tasks with the parent's
owner and options. The gateway queues every frame's first stage at once (a Celery group).
There is no result backend, so the job store counts the frames: a frame's end (its asset
stored, or its failure) is counted in the parent once (``frame_counted``), and the count that
completes the sequence also claims the sequence's export with a conditional UPDATE, so exactly
one frame queues it. The export (`workers.sequence_export`) writes ``sequence.json`` (the
viewer's manifest) as the parent's asset; the parent succeeds when at least one frame did and
lists the failed ones.

The gateway imports this module (it makes sequences and cancels them), so it stays free of
the pipeline.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from sqlalchemy import CursorResult, select, update
from sqlalchemy.orm import Session, sessionmaker

from workers.celery_app import QUEUE_CPU, TASK_SEQUENCE
from workers.models import TERMINAL_STATES, Job, utcnow

log = logging.getLogger(__name__)

LIVE = ("queued", "running")
FRAMES_STAGE = "frames"
"""A sequence job's first stage: its frame jobs run."""
SEQUENCE_EXPORT_STAGE = "export"
"""A sequence job's last stage: the manifest of its frames' meshes."""
SEQUENCE_STAGES = [FRAMES_STAGE, SEQUENCE_EXPORT_STAGE]

SendTask = Callable[[str, list[Any], str], str]


def frame_over(sessions: sessionmaker[Session], job_id: str, send: SendTask) -> bool:
    """Count the end of frame job ``job_id`` in its sequence (once, however often called);
    queue the sequence's export when it was the last frame. True when this call queued it.

    The export is sent before the count commits: a send that fails rolls the count back and
    raises, and the retried or redelivered task of the ended frame counts it again
    (`workers.runner.run_step`). A send whose commit then fails queues an export that finds
    the sequence incomplete and does nothing."""
    with sessions.begin() as session:
        row = session.execute(select(Job.parent_id, Job.state, Job.error, Job.frame_index)
                              .where(Job.id == job_id)).first()
        if row is None or row.parent_id is None or row.state not in TERMINAL_STATES:
            return False
        counted: CursorResult[Any] = session.execute(  # type: ignore[assignment]
            update(Job).where(Job.id == job_id, Job.frame_counted.is_(None))
            .values(frame_counted=True))
        if not counted.rowcount:
            return False
        _count_in_parent(session, row.parent_id, row.state == "succeeded",
                         row.frame_index, row.error or row.state)
        claimed = claim_export(session, row.parent_id)
        if claimed:
            send(TASK_SEQUENCE, [row.parent_id], QUEUE_CPU)
    if claimed:
        log.info("sequence %s: last frame over (frame job %s); export queued",
                 row.parent_id, job_id)
    return claimed


def count_ended_frames(sessions: sessionmaker[Session], parent_id: str, send: SendTask) -> None:
    """Count every ended frame of the sequence not yet counted (a frame whose count was lost
    with its worker); the last one queues the export."""
    with sessions() as session:
        uncounted = list(session.scalars(select(Job.id).where(
            Job.parent_id == parent_id, Job.state.in_(TERMINAL_STATES),
            Job.frame_counted.is_(None))))
    for job_id in uncounted:
        frame_over(sessions, job_id, send)


def _count_in_parent(session: Session, parent_id: str, succeeded: bool,
                     frame_index: int | None, why: str) -> None:
    # Increments in SQL (not read-modify-write), so frames ending at once all count.
    parent = Job.__table__.c
    values: dict[str, Any] = {"updated_at": utcnow()}
    if succeeded:
        values["frames_done"] = parent.frames_done + 1
    else:
        values["frames_failed"] = parent.frames_failed + 1
    session.execute(update(Job).where(Job.id == parent_id).values(**values))
    job = session.get(Job, parent_id, with_for_update=True)
    if job is None:
        return
    if not succeeded:
        job.frame_errors = {**(job.frame_errors or {}), str(frame_index): why[:1000]}
    over = (job.frames_done or 0) + (job.frames_failed or 0)
    if job.state in LIVE and job.frames_total:
        job.progress = min(0.99, over / job.frames_total)


def claim_export(session: Session, parent_id: str) -> bool:
    """Claim the sequence's export once every frame is over: one conditional UPDATE, so of the
    frames that find the count complete exactly one wins."""
    result: CursorResult[Any] = session.execute(  # type: ignore[assignment]
        update(Job).where(Job.id == parent_id, Job.state.in_(LIVE),
                          Job.stage != SEQUENCE_EXPORT_STAGE,
                          Job.frames_done + Job.frames_failed >= Job.frames_total)
        .values(stage=SEQUENCE_EXPORT_STAGE, stage_index=1, done_count=1, state="running",
                updated_at=utcnow()))
    return bool(result.rowcount)


def mark_running(session: Session, frame_job_id: str) -> None:
    """A frame started: its queued sequence is running."""
    parent_id = select(Job.parent_id).where(Job.id == frame_job_id).scalar_subquery()
    now = utcnow()
    session.execute(update(Job).where(Job.id == parent_id, Job.state == "queued")
                    .values(state="running", started_at=now, updated_at=now))
