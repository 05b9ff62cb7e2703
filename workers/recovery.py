"""Picking up, when the embedded service starts, the jobs whose task message may be lost.

The embedded file-system broker forgets a task that a worker had taken when that worker died.
A stage that was running holds a lease, and the gateway's sweep queues it again once the lease
lapses (`workers.leases`); a job holding no lease (queued, or between two stages) has no such
keeper, so ``volumesh serve`` queues each one again at its next stage on start; a sequence
job gets its export task (which does nothing until all its frames are over). Duplicate
deliveries are harmless (a stage already counted is skipped; stored outputs are reused).
"""

from __future__ import annotations

from sqlalchemy import select

from workers.celery_app import QUEUE_CPU, TASK_SEQUENCE, TASK_STAGE, make_celery, queue_for_stage
from workers.db import init_db, make_engine, make_sessionmaker
from workers.leases import LIVE
from workers.models import Job
from workers.settings import Settings


def requeue_unfinished(settings: Settings) -> list[str]:
    """Queue the next stage of every queued or running job that holds no lease; returns their
    ids."""
    engine = make_engine(settings)
    init_db(engine)
    sessions = make_sessionmaker(engine)
    with sessions() as session:
        rows = list(session.execute(select(Job.id, Job.done_count, Job.stages, Job.frames_total)
                                    .where(Job.state.in_(LIVE), Job.lease_owner.is_(None))))
    engine.dispose()
    if not rows:
        return []
    celery = make_celery(settings)
    for job_id, done, stages, frames_total in rows:
        if frames_total is not None:
            celery.send_task(TASK_SEQUENCE, args=[job_id], queue=QUEUE_CPU, routing_key=QUEUE_CPU)
            continue
        stage = stages[done] if stages and done < len(stages) else ""
        queue = queue_for_stage(stage)
        celery.send_task(TASK_STAGE, args=[job_id, done], queue=queue, routing_key=queue)
    return [row[0] for row in rows]
