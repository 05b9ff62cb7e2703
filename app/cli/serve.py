"""`volumesh serve`: the gateway, plus an embedded worker when no broker is configured.

With no settings everything lives in ``VOLUMESH_DATA_DIR`` (SQLite job store, file-system broker,
local storage) and two worker processes run beside the gateway: one for stages, one for upload
validation (so an upload never waits behind a long stage). With ``VOLUMESH_BROKER_URL`` set the
gateway runs alone and ``volumesh worker`` processes anywhere do the work.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Annotated, Any

import typer

from app.cli import app

_EMBEDDED_WORKERS = (("stages", "cpu,gpu"), ("uploads", "validate"))


def _die_with_parent() -> None:
    # Linux: the worker gets SIGTERM when serve dies, even by SIGKILL, so none is orphaned.
    with contextlib.suppress(Exception):
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


class _Workers:
    """Embedded worker processes, restarted if one dies while the gateway runs."""

    def __init__(self, log_dir: Path) -> None:
        self.log_dir = log_dir
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self.stopping = threading.Event()

    def _start(self, name: str, queues: str) -> None:
        self.log_dir.mkdir(parents=True, exist_ok=True)
        cmd = [sys.executable, "-m", "workers", "--queues", queues, "--concurrency", "1",
               "--hostname", f"embedded-{name}.{os.getpid()}@localhost"]
        self.procs[name] = subprocess.Popen(cmd, preexec_fn=_die_with_parent,  # noqa: PLW1509
                                            start_new_session=True)

    def start(self) -> None:
        for name, queues in _EMBEDDED_WORKERS:
            self._start(name, queues)
        threading.Thread(target=self._watch, daemon=True).start()

    def _watch(self) -> None:
        while not self.stopping.wait(1.0):
            for name, queues in _EMBEDDED_WORKERS:
                proc = self.procs.get(name)
                if proc is not None and proc.poll() is not None and not self.stopping.is_set():
                    typer.echo(f"volumesh serve: embedded worker {name} exited "
                               f"({proc.returncode}); restarting it", err=True)
                    self._start(name, queues)

    def stop(self, grace_s: float = 10.0) -> None:
        self.stopping.set()
        for proc in self.procs.values():
            with contextlib.suppress(ProcessLookupError):
                proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + grace_s
        for proc in self.procs.values():
            try:
                proc.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()


def _exit_on_signal(signum: int, _frame: Any) -> None:
    raise SystemExit(0)


def _bootstrap_key(settings: Any) -> None:
    """First start of an embedded service: create an admin key so the one user of a laptop
    install sees everything at once (keys for others: `volumesh keys create`)."""
    from app.core.security import create_key
    from workers.db import init_db, make_engine, make_sessionmaker
    from workers.models import ApiKey

    engine = make_engine(settings)
    init_db(engine)
    with make_sessionmaker(engine)() as session:
        if session.query(ApiKey).count():
            return
        _, key = create_key(session, "bootstrap", admin=True)
    path = settings.data_dir / "api-key.txt"
    path.write_text(key + "\n")
    path.chmod(0o600)
    typer.echo(f"volumesh serve: created the first API key (an admin key), saved in {path}:\n"
               f"{key}", err=True)


@app.command()
def serve(
    host: Annotated[str, typer.Option("--host", help="Address to listen on.")] = "127.0.0.1",
    port: Annotated[int, typer.Option("--port", min=1, max=65535)] = 8000,
    workers: Annotated[int, typer.Option("--workers", min=1, max=64,
                                         help="Gateway processes (uvicorn workers).")] = 1,
    sample: Annotated[bool, typer.Option("--sample", help="Store a synthetic sample capture "
                                         "ready to process.")] = False,
    data_dir: Annotated[Path | None, typer.Option(
        "--data-dir", help="Overrides VOLUMESH_DATA_DIR.")] = None,
    log_level: Annotated[str, typer.Option("--log-level")] = "info",
) -> None:
    """Runs the service until stopped (Ctrl-C)."""
    import uvicorn

    from workers.recovery import requeue_unfinished
    from workers.settings import get_settings

    if data_dir is not None:
        os.environ["VOLUMESH_DATA_DIR"] = str(data_dir)
    settings = get_settings()
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    embedded_workers: _Workers | None = None
    if settings.embedded:
        _bootstrap_key(settings)
    if sample:
        from app.cli.sample import store_sample

        capture_id = store_sample(settings)
        key_file = settings.data_dir.resolve() / "api-key.txt"
        key = f"$(cat {key_file})" if key_file.is_file() else "YOUR_API_KEY"
        typer.echo(f"volumesh serve: sample capture {capture_id} is ready; start a job with\n"
                   f"  curl -X POST http://{host}:{port}/api/v1/jobs -H \"Authorization: Bearer "
                   f"{key}\" -H 'Content-Type: application/json' -d "
                   f"'{{\"capture_id\": \"{capture_id}\", \"enhance\": false}}'\n"
                   f"  then open http://{host}:{port}/ to watch it", err=True)
    if settings.embedded and settings.embedded_worker:
        requeue_unfinished(settings)
        embedded_workers = _Workers(settings.data_dir / "logs")
        embedded_workers.start()
    # uvicorn re-raises SIGTERM once it has shut down; with the default handler that would end
    # this process before it stops the embedded workers, so turn it into SystemExit.
    signal.signal(signal.SIGTERM, _exit_on_signal)
    try:
        uvicorn.run("app.main:app_from_env", factory=True, host=host, port=port,
                    workers=workers, log_level=log_level, timeout_graceful_shutdown=10)
    finally:
        if embedded_workers is not None:
            embedded_workers.stop()
