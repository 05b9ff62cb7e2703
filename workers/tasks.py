"""Thin Celery tasks: ids in, work in :mod:`workers.runner` (a stage),
:mod:`workers.captures` (an upload's validation) and :mod:`workers.streams` (a closed stream's
assembly), state to the job store.

The gateway sends these by name (``volumesh.stage``, ``volumesh.validate_capture``,
``volumesh.assemble_stream``) and never imports this module.
"""

from __future__ import annotations

import logging
from typing import Any

from celery import Task, shared_task
from celery.exceptions import SoftTimeLimitExceeded
from celery.signals import worker_process_init, worker_ready, worker_shutdown

from workers import presence
from workers.captures import validate_capture
from workers.celery_app import TASK_ASSEMBLE, TASK_SEQUENCE, TASK_STAGE, TASK_VALIDATE
from workers.context import WorkerContext
from workers.runner import JobCancelledError, SendTask, run_step, stage_name
from workers.sequence import count_ended_frames, frame_over
from workers.sequence_export import export_sequence
from workers.settings import Settings, get_settings
from workers.streams import assemble_stream, delete_chunks_if_over, finish_stream

log = logging.getLogger(__name__)

_contexts: dict[int, WorkerContext] = {}


def _transient_errors() -> tuple[type[BaseException], ...]:
    """Errors worth a retry: the network, the database or the storage hiccuped."""
    from botocore.exceptions import BotoCoreError
    from kombu.exceptions import OperationalError as BrokerError
    from sqlalchemy.exc import InterfaceError, OperationalError

    return (OSError, ConnectionError, TimeoutError, OperationalError, InterfaceError,
            BotoCoreError, BrokerError)


def _context(task: Task) -> WorkerContext:
    settings: Settings = getattr(task.app, "volumesh_settings", None) or get_settings()
    ctx = _contexts.get(id(settings))
    if ctx is None:
        ctx = _contexts[id(settings)] = WorkerContext.create(settings)
    return ctx


@worker_process_init.connect
def _prepare_process(**_: Any) -> None:
    # Celery's pool processes are daemonic, and a daemonic process may not start children;
    # the remesh stage runs its native kernel in a child so a crash there fails the stage
    # instead of killing (and endlessly redelivering) the task.
    # Billiard (Celery's fork of multiprocessing) also leaves an authkey type the standard
    # library refuses to pickle into a spawned child; hand it a plain one.
    import multiprocessing
    import multiprocessing.process

    config = multiprocessing.current_process()._config  # type: ignore[attr-defined]
    config.pop("daemon", None)
    plain_key = multiprocessing.process.AuthenticationString  # type: ignore[attr-defined]
    config["authkey"] = plain_key(bytes(config["authkey"]))
    # Load the pipeline once per worker process, not on a job's clock.
    import pipeline.io.capture_io  # noqa: F401

    try:
        import pipeline.stages  # noqa: F401
    except ImportError:
        log.warning("pipeline.stages is missing: stage tasks will fail")


@worker_ready.connect
def _announce(sender: Any, **_: Any) -> None:
    # The worker's main process records itself and its queues in the job store while it runs,
    # so the gateway can tell a job that waits on a queue nobody consumes (no broadcast needed).
    presence.start_announcing(sender)


@worker_shutdown.connect
def _retire(**_: Any) -> None:
    presence.stop_announcing()


def _backoff_s(retries: int) -> float:
    return float(min(60, 2 ** retries))


@shared_task(bind=True, name=TASK_STAGE)
def stage(self: Task, job_id: str, index: int) -> None:
    """Run stage ``index`` of job ``job_id`` and queue the next one."""
    ctx = _context(self)

    send = _sender(self)

    def fail(error: str) -> None:
        if ctx.store.fail(job_id, error):
            frame_over(ctx.store.sessions, job_id, send)  # a frame of a sequence: count it

    try:
        run_step(ctx, job_id, index, self.request.id, send)
    except JobCancelledError:
        log.info("job %s cancelled during stage %d", job_id, index)
    except ValueError as exc:
        fail(str(exc))
    except SoftTimeLimitExceeded:
        fail(f"{stage_name(ctx, job_id, index)} ran longer than the "
             f"{ctx.settings.task_soft_time_limit_s} s limit (VOLUMESH_TASK_SOFT_TIME_LIMIT_S)")
    except _transient_errors() as exc:
        if self.request.retries >= ctx.settings.task_max_retries:
            fail(f"{stage_name(ctx, job_id, index)} gave up after "
                 f"{self.request.retries} retries: {type(exc).__name__}: {exc}")
            return
        log.warning("job %s stage %d: transient %r, retrying", job_id, index, exc)
        raise self.retry(exc=exc, countdown=_backoff_s(self.request.retries),
                         max_retries=ctx.settings.task_max_retries) from exc
    except Exception as exc:
        log.exception("job %s stage %d failed unexpectedly", job_id, index)
        fail(f"internal error in {stage_name(ctx, job_id, index)}: {type(exc).__name__}: {exc}")


def _sender(task: Task) -> SendTask:
    def send(name: str, args: list[Any], queue: str) -> str:
        return str(task.app.send_task(name, args=args, queue=queue, routing_key=queue).id)

    return send


@shared_task(bind=True, name=TASK_SEQUENCE)
def sequence(self: Task, job_id: str) -> None:
    """Write sequence job ``job_id``'s manifest once all its frames are over."""
    ctx = _context(self)
    try:
        count_ended_frames(ctx.store.sessions, job_id, _sender(self))
        export_sequence(ctx, job_id)
    except _transient_errors() as exc:
        if self.request.retries >= ctx.settings.task_max_retries:
            ctx.store.fail(job_id, f"the sequence export gave up after {self.request.retries} "
                           f"retries: {type(exc).__name__}: {exc}")
            return
        raise self.retry(exc=exc, countdown=_backoff_s(self.request.retries),
                         max_retries=ctx.settings.task_max_retries) from exc
    except Exception as exc:
        log.exception("sequence %s: export failed unexpectedly", job_id)
        ctx.store.fail(job_id, f"internal error in the sequence export: "
                       f"{type(exc).__name__}: {exc}")


@shared_task(bind=True, name=TASK_VALIDATE, soft_time_limit=540, time_limit=600)
def validate(self: Task, capture_id: str) -> None:
    """Read an uploaded capture whole; mark it ready or rejected (with the reader's message)."""
    ctx = _context(self)
    try:
        validate_capture(ctx, capture_id)
    except SoftTimeLimitExceeded:
        ctx.store.capture_rejected(capture_id, "reading the capture took longer than 540 s")
    except _transient_errors() as exc:
        if self.request.retries >= ctx.settings.task_max_retries:
            ctx.store.capture_rejected(capture_id, f"the worker could not fetch the stored "
                                       f"capture after {self.request.retries} retries "
                                       f"({type(exc).__name__}: {exc}); upload it again")
            return
        raise self.retry(exc=exc, countdown=_backoff_s(self.request.retries),
                         max_retries=ctx.settings.task_max_retries) from exc
    except Exception as exc:  # never leave the upload waiting on a capture stuck `validating`
        log.exception("validating capture %s failed unexpectedly", capture_id)
        ctx.store.capture_rejected(capture_id, f"internal error while validating the capture "
                                   f"({type(exc).__name__}: {exc})")


@shared_task(bind=True, name=TASK_ASSEMBLE)
def assemble(self: Task, stream_id: str) -> None:
    """Write a closed stream's frame-sets into one capture; mark it closed or failed (why)."""
    ctx = _context(self)

    def fail(error: str) -> None:
        finish_stream(ctx, stream_id, error=error)
        delete_chunks_if_over(ctx, stream_id)

    try:
        assemble_stream(ctx, stream_id)
    except SoftTimeLimitExceeded:
        fail(f"assembling the capture took longer than {ctx.settings.task_soft_time_limit_s} s "
             "(VOLUMESH_TASK_SOFT_TIME_LIMIT_S)")
    except _transient_errors() as exc:
        if self.request.retries >= ctx.settings.task_max_retries:
            fail(f"the assembly gave up after {self.request.retries} retries "
                 f"({type(exc).__name__}: {exc})")
            return
        raise self.retry(exc=exc, countdown=_backoff_s(self.request.retries),
                         max_retries=ctx.settings.task_max_retries) from exc
    except Exception as exc:  # never leave the stream `assembling` for good
        log.exception("assembling stream %s failed unexpectedly", stream_id)
        fail(f"internal error while assembling the capture ({type(exc).__name__}: {exc})")
