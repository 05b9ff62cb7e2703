"""Starting a Celery worker process for the service's settings."""

from __future__ import annotations

import argparse
import os
import socket

from workers.celery_app import QUEUES, make_celery
from workers.settings import Settings, get_settings


def parse_queues(text: str) -> list[str]:
    queues = [q.strip() for q in text.split(",") if q.strip()]
    unknown = sorted(set(queues) - set(QUEUES))
    if not queues or unknown:
        raise ValueError(f"--queues: {text!r}: choose among {', '.join(QUEUES)}")
    return queues


def worker_argv(queues: list[str], concurrency: int, hostname: str, loglevel: str,
                pool: str = "prefork") -> list[str]:
    return ["worker", "--queues", ",".join(queues), "--concurrency", str(concurrency),
            "--hostname", hostname, "--loglevel", loglevel, "--pool", pool,
            # Gossip, mingle and heartbeats only matter for monitoring tools; they slow the
            # start and need broadcast, which the embedded broker lacks.
            "--without-gossip", "--without-mingle", "--without-heartbeat"]


def run_worker(settings: Settings, queues: list[str], *, concurrency: int | None = None,
               hostname: str | None = None, loglevel: str = "INFO") -> None:
    """Run a worker in this process until it is stopped (SIGTERM: finish the task, then stop)."""
    app = make_celery(settings)
    app.set_current()
    app.set_default()
    name = hostname or f"{'-'.join(queues)}.{os.getpid()}@{socket.gethostname()}"
    app.worker_main(worker_argv(queues, concurrency or settings.worker_concurrency, name,
                                loglevel))


def main(argv: list[str] | None = None) -> None:
    """``python -m workers --queues cpu,gpu`` (``volumesh worker`` is the same)."""
    parser = argparse.ArgumentParser(prog="python -m workers")
    parser.add_argument("--queues", default=",".join(QUEUES))
    parser.add_argument("--concurrency", type=int, default=None)
    parser.add_argument("--hostname", default=None)
    parser.add_argument("--loglevel", default="INFO")
    args = parser.parse_args(argv)
    try:
        queues = parse_queues(args.queues)
    except ValueError as exc:
        parser.error(str(exc))
    run_worker(get_settings(), queues, concurrency=args.concurrency, hostname=args.hostname,
               loglevel=args.loglevel)
