"""`volumesh worker`: a Celery worker for a shared broker (Redis), any number, any machine."""

from __future__ import annotations

from typing import Annotated

import typer

from app.cli import app


@app.command()
def worker(
    queues: Annotated[str, typer.Option(
        "--queues", help="Queues to take tasks from: cpu (stages), gpu (LDM enhancement), "
        "validate (uploads).")] = "cpu,gpu,validate",
    concurrency: Annotated[int | None, typer.Option(
        "--concurrency", min=1, help="Worker processes (default VOLUMESH_WORKER_CONCURRENCY).")
    ] = None,
    hostname: Annotated[str | None, typer.Option("--hostname", help="Celery node name.")] = None,
    loglevel: Annotated[str, typer.Option("--loglevel")] = "INFO",
) -> None:
    """Runs stage tasks from the broker in VOLUMESH_BROKER_URL until stopped (SIGTERM)."""
    from workers.settings import get_settings
    from workers.worker import parse_queues, run_worker

    chosen = parse_queues(queues)
    settings = get_settings()
    if settings.embedded:
        typer.echo("volumesh worker: VOLUMESH_BROKER_URL is unset, so this worker shares the "
                   f"embedded file-system broker in {settings.data_dir.resolve()}", err=True)
    run_worker(settings, chosen, concurrency=concurrency, hostname=hostname,
               loglevel=loglevel)
