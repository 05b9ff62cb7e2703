"""`volumesh agent`: streams a rig's frame-sets to a gateway (the edge capture agent)."""

from __future__ import annotations

import json
import signal
import sys
import threading
from pathlib import Path
from typing import Annotated, Any

import typer

from app.cli import app

STATUS_EVERY_S_NOT_TTY = 5.0
"""Without a terminal (a log file, a service) the status goes as a line every few seconds."""


@app.command()
def agent(
    gateway: Annotated[str, typer.Option("--gateway", help="The gateway's URL, e.g. "
                                         "http://127.0.0.1:8000.")],
    source: Annotated[str, typer.Option(
        "--source", help="mkv:A.mkv,B.mkv,... (Azure Kinect recordings, one per device), "
        "capture:DIR (a capture directory or zip with many frames), synthetic (the simulated "
        "8-camera rig, a moving subject) or k4a (live devices; needs volumesh[k4a]).")],
    key: Annotated[str | None, typer.Option(
        "--key", envvar="VOLUMESH_API_KEY", show_envvar=True, help="API key.")] = None,
    spool: Annotated[Path, typer.Option(
        "--spool", help="Folder of frame-sets not sent yet; the same --spool and --source "
        "resume an interrupted stream.")] = Path("volumesh-spool"),
    spool_max_gb: Annotated[float, typer.Option(
        "--spool-max-gb", help="Spool size cap, GB: a replay waits, a live source drops "
        "frame-sets while it is full.")] = 20.0,
    fast: Annotated[bool, typer.Option("--fast", help="Replay as fast as possible, not at "
                                       "the source's frame rate.")] = False,
    fps: Annotated[float | None, typer.Option(
        "--fps", help="Frame rate of the synthetic rig and of a capture without frame "
        "timestamps (default 30).")] = None,
    frames: Annotated[int, typer.Option("--frames", help="Frame-sets of the synthetic "
                                        "source.")] = 300,
    rig: Annotated[str | None, typer.Option(
        "--rig", help="A rig's id: the stream takes its camera poses (live preview and "
        "reconstruction of sources without poses).")] = None,
    name: Annotated[str | None, typer.Option("--name", help="The stream's name.")] = None,
    preview_hz: Annotated[float, typer.Option(
        "--preview-hz", help="Live previews per second of capture (0: none); needs every "
        "camera's pose.")] = 10.0,
) -> None:
    """Captures frame-sets from SOURCE into a spool on disk and sends them to the gateway as a
    stream; at the source's end closes the stream and prints the capture it became.

    When the gateway is away, capture goes on into the spool and everything is sent when it
    is back. Ctrl-C or SIGTERM stops (exit 130/143) and keeps the spool: the same command
    resumes the same stream where it stopped.
    """
    from agent.run import GB, AgentConfig, run_agent
    from agent.sources import SourceOptions

    config = AgentConfig(gateway_url=gateway, api_key=key or "", source=source,
                         spool_dir=spool, spool_max_bytes=int(spool_max_gb * GB), fast=fast,
                         source_options=SourceOptions(fps=fps, frames=frames), rig_id=rig,
                         name=name, preview_hz=preview_hz)
    stop = threading.Event()
    signals = _Signals(stop)
    status = _StatusLine()
    _log_to(status)
    result = run_agent(config, stop, status.show)
    status.end()
    _report(result, signals.received)


class _Signals:
    """SIGINT and SIGTERM set ``stop`` (the agent stops capturing and keeps the spool); a
    second one exits at once."""

    def __init__(self, stop: threading.Event) -> None:
        self.stop = stop
        self.received: int | None = None
        signal.signal(signal.SIGINT, self._handle)
        signal.signal(signal.SIGTERM, self._handle)

    def _handle(self, signum: int, _: Any) -> None:
        if self.received is not None:
            raise SystemExit(128 + signum)
        self.received = signum
        self.stop.set()


class _StatusLine:
    """The agent's status on stderr: one refreshed line on a terminal, else a line every
    few seconds; at the end, the whole run's averages."""

    def __init__(self) -> None:
        self.tty = sys.stderr.isatty()
        self.first: Any = None
        self.last: Any = None
        self.reference: Any = None
        """The snapshot rates are counted from: the last 0.5-2 s (terminal), or since the
        last line printed."""

    def show(self, snapshot: Any) -> None:
        from agent.stats import status_line

        self.first = self.first or snapshot
        self.reference = self.reference or snapshot
        self.last = snapshot
        if self.tty:
            sys.stderr.write("\r\033[K" + status_line(self.reference, snapshot))
            sys.stderr.flush()
            if snapshot.at_s - self.reference.at_s >= 2.0:
                self.reference = snapshot
        elif snapshot.at_s - self.reference.at_s >= STATUS_EVERY_S_NOT_TTY:
            print(status_line(self.reference, snapshot), file=sys.stderr, flush=True)
            self.reference = snapshot

    def clear(self) -> None:
        if self.tty and self.last is not None:
            sys.stderr.write("\r\033[K")

    def end(self) -> None:
        from agent.stats import status_line

        if self.last is not None:
            self.clear()
            print(status_line(self.first, self.last), file=sys.stderr, flush=True)


def _log_to(status: _StatusLine) -> None:
    """The agent's log lines on stderr, clear of the status line."""
    import logging

    class Handler(logging.StreamHandler):  # type: ignore[type-arg]
        def emit(self, record: logging.LogRecord) -> None:
            status.clear()
            super().emit(record)

    handler = Handler(sys.stderr)
    handler.setFormatter(logging.Formatter("volumesh agent: %(message)s"))
    logger = logging.getLogger("agent")
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    logger.propagate = False


def _report(result: Any, signum: int | None) -> None:
    if result.state == "interrupted":
        typer.echo(f"stopped: the spool keeps stream {result.stream_id}; run the same command "
                   "to resume it" if result.stream_id else "stopped before a stream began",
                   err=True)
        raise typer.Exit(128 + (signum or signal.SIGINT))
    if result.stats is not None and result.stats.rejected:
        typer.echo(f"{result.stats.rejected} frame-set(s) refused by the gateway: see the "
                   "spool's rejected/ folder", err=True)
    if result.state != "closed":
        typer.echo(f"volumesh: error: stream {result.stream_id} {result.state}: "
                   f"{result.error}", err=True)
        raise typer.Exit(1)
    typer.echo(f"capture {result.capture_id}: {result.frames_received} frame-set(s) from "
               f"stream {result.stream_id}")
    body = json.dumps({"capture_id": result.capture_id, "frames": "all"})
    typer.echo(f"next: curl -X POST {result.gateway_url}/api/v1/jobs "
               f"-H \"Authorization: Bearer $VOLUMESH_API_KEY\" "
               f"-H 'Content-Type: application/json' -d '{body}'")
