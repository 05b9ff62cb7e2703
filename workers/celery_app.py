"""The Celery app, configured from the service :class:`~workers.settings.Settings`.

Queues: ``cpu`` (reconstruction stages), ``gpu`` (the LDM enhancement stage, so GPU machines
take only that) and ``validate`` (quick reads of a freshly uploaded capture, and the assembly
of a closed stream, kept apart so an upload never waits behind a long stage). Tasks are
acknowledged after they finish and handed back when their worker dies, one task at a time per
process.

``celery -A workers.celery_app worker`` works (``app`` is built from the environment on first
use); ``volumesh worker`` is the usual way in.
"""

from __future__ import annotations

from typing import Any

from celery import Celery
from kombu import Exchange, Queue

from workers import fs_broker
from workers.settings import Settings, get_settings

QUEUE_CPU = "cpu"
QUEUE_GPU = "gpu"
QUEUE_VALIDATE = "validate"
QUEUES = (QUEUE_CPU, QUEUE_GPU, QUEUE_VALIDATE)
GPU_STAGES = frozenset({"enhance"})
"""Stages that run on the gpu queue."""

TASK_STAGE = "volumesh.stage"
TASK_VALIDATE = "volumesh.validate_capture"
TASK_ASSEMBLE = "volumesh.assemble_stream"
"""A closed stream's frame-sets into one capture (`workers.streams`); on the validate queue, as
it ends in reading that capture whole."""
TASK_SEQUENCE = "volumesh.sequence"
"""A sequence job's export: its manifest, once every frame is over (`workers.sequence`)."""


def queue_for_stage(stage: str) -> str:
    return QUEUE_GPU if stage in GPU_STAGES else QUEUE_CPU


def _embedded_broker(settings: Settings) -> tuple[str, dict[str, Any]]:
    folder = settings.broker_dir.resolve()
    for sub in ("queue", "processed", "control"):
        (folder / sub).mkdir(parents=True, exist_ok=True)
    return f"{fs_broker.SCHEME}://localhost//", {
        "data_folder_in": str(folder / "queue"),
        "data_folder_out": str(folder / "queue"),
        "processed_folder": str(folder / "processed"),
        "control_folder": str(folder / "control"),
        "store_processed": False,
        "polling_interval": settings.broker_polling_interval_s,
    }


def _redis_options(settings: Settings) -> dict[str, Any]:
    return {
        # A task whose worker died goes back to the queue after this: a backstop, as the
        # stage's lapsed lease has it queued again long before (workers.leases).
        "visibility_timeout": settings.visibility_timeout_s,
        "unacked_restore_interval": max(1, min(10, settings.visibility_timeout_s // 4)),
        "unacked_restore_throttle": 1,
        "socket_connect_timeout": 5,
        "socket_timeout": 30,
        "retry_on_timeout": True,
        "health_check_interval": 10,
    }


def make_celery(settings: Settings) -> Celery:
    """A Celery app for these settings (tasks are registered by importing workers.tasks)."""
    if settings.broker_url is None:
        broker_url, transport_options = _embedded_broker(settings)
    else:
        broker_url = settings.broker_url
        transport_options = _redis_options(settings) if broker_url.startswith("redis") else {}
    app = Celery("volumesh", broker=broker_url, include=["workers.tasks"], set_as_current=False)
    exchange = Exchange("volumesh", type="direct")
    app.conf.update(
        broker_transport_options=transport_options,
        broker_connection_retry_on_startup=True,
        broker_connection_max_retries=None,
        task_queues=[Queue(name, exchange, routing_key=name) for name in QUEUES],
        task_default_queue=QUEUE_CPU,
        task_default_exchange="volumesh",
        task_default_routing_key=QUEUE_CPU,
        task_routes={name: {"queue": QUEUE_VALIDATE, "routing_key": QUEUE_VALIDATE}
                     for name in (TASK_VALIDATE, TASK_ASSEMBLE)},
        task_serializer="json",
        accept_content=["json"],
        task_ignore_result=True,  # results go to the job store, not a result backend
        result_backend=None,
        task_acks_late=True,
        task_reject_on_worker_lost=True,
        task_acks_on_failure_or_timeout=True,
        worker_prefetch_multiplier=1,
        worker_concurrency=settings.worker_concurrency,
        task_time_limit=settings.task_time_limit_s,
        task_soft_time_limit=settings.task_soft_time_limit_s,
        task_publish_retry=True,
        task_publish_retry_policy={"max_retries": 20, "interval_start": 0.2,
                                   "interval_step": 0.5, "interval_max": 3.0},
        worker_hijack_root_logger=False,
        worker_send_task_events=False,
        worker_enable_remote_control=settings.broker_url is not None,
        broker_heartbeat=0,
        enable_utc=True,
    )
    app.volumesh_settings = settings  # type: ignore[attr-defined]
    return app


def __getattr__(name: str) -> Any:
    # `celery -A workers.celery_app` looks up `app`; build it only then, from the environment.
    if name == "app":
        app = make_celery(get_settings())
        globals()["app"] = app
        return app
    raise AttributeError(name)
