"""The agent from start to end: the stream created (or resumed from the spool), the source
captured into the spool while senders empty it, then the stream closed and its capture
awaited. Stopping (Ctrl-C, SIGTERM) keeps the spool: the same command resumes."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from agent.capture import CaptureSettings, posed, run_capture
from agent.gateway import Gateway, RefusedError, StoppedError, check_url
from agent.preview_sender import PreviewSender
from agent.sender import Senders
from agent.sources import Source, SourceInfo, SourceOptions, open_source
from agent.spool import Spool, SpoolState
from agent.stats import Snapshot, Stats
from pipeline.capture import FORMAT_ID, CameraInfo, CaptureMeta
from pipeline.io.capture_json import meta_from_json, meta_to_json

GB = 1_000_000_000
REPORT_INTERVAL_S = 0.5
POLL_INTERVAL_S = 0.5


@dataclass(frozen=True)
class AgentConfig:
    gateway_url: str
    api_key: str
    source: str
    spool_dir: Path = Path("volumesh-spool")
    spool_max_bytes: int = 20 * GB
    fast: bool = False
    source_options: SourceOptions = field(default_factory=SourceOptions)
    rig_id: str | None = None
    name: str | None = None
    preview_hz: float = 10.0
    senders: int = 4
    """Frame-sets in flight at once."""
    connect_deadline_s: float = 30.0
    """How long a new stream waits for an unreachable gateway before giving up."""

    def __post_init__(self) -> None:
        if not self.api_key:
            raise ValueError("--key: no API key (pass --key or set VOLUMESH_API_KEY)")
        check_url(self.gateway_url)
        if self.spool_max_bytes <= 0:
            raise ValueError("--spool-max-gb: must be positive")
        if self.preview_hz < 0:
            raise ValueError(f"--preview-hz: must be 0 (none) or more, got {self.preview_hz:g}")
        if self.name is not None and len(self.name) > 100:
            raise ValueError("--name: at most 100 characters")
        if self.senders < 1:
            raise ValueError("senders: at least 1")


@dataclass(frozen=True)
class AgentResult:
    stream_id: str
    state: str
    """closed, failed, or interrupted (the spool kept for a resume)."""
    capture_id: str | None = None
    frames_received: int = 0
    error: str | None = None
    gateway_url: str = ""
    stats: Snapshot | None = None


def run_agent(config: AgentConfig, stop: threading.Event,
              report: Callable[[Snapshot], None] | None = None) -> AgentResult:
    """Runs the agent until its source is sent and its capture made, or ``stop``. ValueError
    of one line for bad input (source, spool, key, rig, an unreachable gateway)."""
    url = check_url(config.gateway_url)
    source = open_source(config.source, config.source_options)  # bad input fails first
    try:
        spool = Spool(config.spool_dir, config.spool_max_bytes)
        state = spool.read_state()
        check_resumable(spool, state, config.source, url)
    except BaseException:
        source.close()
        raise
    gateway = Gateway(url, config.api_key, connections=config.senders)
    stats = Stats()
    try:
        if state is None:
            if stop.is_set():  # asked to stop while the source opened: no stream to leave
                raise StoppedError()
            state = create_stream(gateway, source.info, config, stop, stats)
            spool.write_state(state)
        else:
            spool.drop_from(state.next_index)
        with reporting(stats, spool, report):
            result = _stream(config, source, gateway, spool, state, stats, stop)
        return result
    except StoppedError:
        return AgentResult(state.stream_id if state else "", "interrupted", gateway_url=url)
    finally:
        spool.close()
        source.close()
        gateway.close()


def _stream(config: AgentConfig, source: Source, gateway: Gateway, spool: Spool,
            state: SpoolState, stats: Stats, stop: threading.Event) -> AgentResult:
    senders = Senders(gateway, state.stream_id, spool, stats, config.senders, stop)
    senders.start()
    if not state.source_done:
        settings = CaptureSettings(fast=config.fast, preview_hz=config.preview_hz,
                                   posed_cameras=posed(source.info.cameras,
                                                       stream_cameras(state)))
        previews = PreviewSender(gateway, state.stream_id, stats).start()
        try:
            state = run_capture(source, spool, state, settings, stats, stop, previews.offer)
        finally:
            previews.close()
    if stop.is_set():
        return AgentResult(state.stream_id, "interrupted", gateway_url=gateway.url)
    while not spool.wait_empty(POLL_INTERVAL_S):
        if stop.is_set():
            return AgentResult(state.stream_id, "interrupted", gateway_url=gateway.url)
    stream = close_stream(gateway, state.stream_id, stop, stats)
    spool.clear_state()
    return AgentResult(state.stream_id, stream["state"], stream.get("capture_id"),
                       int(stream.get("frames_received") or 0), stream.get("error"),
                       gateway.url, stats.snapshot(time.monotonic(), *spool.size()))


def check_resumable(spool: Spool, state: SpoolState | None, source: str, url: str) -> None:
    """ValueError where the spool holds another stream's frame-sets."""
    pending, _ = spool.size()
    if state is None:
        if pending:
            raise ValueError(f"--spool: {spool.root} holds {pending} frame-set(s) but no "
                             "state.json; delete the folder to start afresh")
        return
    if (state.source, state.gateway_url) != (source, url):
        raise ValueError(
            f"--spool: {spool.root} holds stream {state.stream_id} of --source "
            f"{state.source} for --gateway {state.gateway_url} ({pending} frame-set(s) unsent); "
            "finish it by running again with that --source and --gateway, or delete the "
            "folder to drop it")


def cameras_json(depth_scale: float, cameras: tuple[CameraInfo, ...]) -> list[dict[str, Any]]:
    """The cameras as capture.json writes them (the stream's body takes them so)."""
    return list(meta_to_json(CaptureMeta(depth_scale, cameras, frames=()))["cameras"])


def stream_cameras(state: SpoolState) -> tuple[CameraInfo, ...]:
    document = {"format": FORMAT_ID, "depth_scale": state.depth_scale,
                "cameras": list(state.cameras), "frames": [{"index": 0}]}
    return meta_from_json(document).cameras


def create_stream(gateway: Gateway, info: SourceInfo, config: AgentConfig,
                  stop: threading.Event, stats: Stats) -> SpoolState:
    body = {"name": config.name, "fps": info.fps, "depth_scale": info.depth_scale,
            "cameras": cameras_json(info.depth_scale, info.cameras), "rig_id": config.rig_id}
    try:
        stream = gateway.call("POST", "/streams", stop, _retrying(stats),
                              deadline_s=config.connect_deadline_s, json=body)
    except TimeoutError as exc:
        raise ValueError(f"--gateway: no answer from {gateway.url} in "
                         f"{config.connect_deadline_s:g} s ({exc})") from None
    except RefusedError as exc:
        raise ValueError(_refusal(exc, config.rig_id)) from None
    stats.set_connection("connected")
    return SpoolState(gateway_url=gateway.url, stream_id=str(stream["id"]),
                      source=config.source, depth_scale=info.depth_scale,
                      cameras=tuple(stream["cameras"]))


def _refusal(exc: RefusedError, rig_id: str | None) -> str:
    if exc.status == 401:
        return f"--key: the gateway refused the API key ({exc})"
    if exc.status == 404 and rig_id is not None:
        return f"--rig: {exc}"
    return f"the gateway refused the stream: {exc}"


def close_stream(gateway: Gateway, stream_id: str, stop: threading.Event,
                 stats: Stats) -> dict[str, Any]:
    """Closes the stream and waits until its capture is made (closed) or failed."""
    on_retry = _retrying(stats)
    try:
        stream = gateway.call("POST", f"/streams/{stream_id}/close", stop, on_retry)
        while stream["state"] not in ("closed", "failed"):
            if stop.wait(POLL_INTERVAL_S):
                raise StoppedError()
            stream = gateway.call("GET", f"/streams/{stream_id}", stop, on_retry)
    except RefusedError as exc:  # 409: no frame-set arrived; 404: the stream is gone
        return {"state": "failed", "error": str(exc)}
    return stream


def _retrying(stats: Stats) -> Callable[[str], None]:
    return lambda reason: stats.set_connection(f"retrying ({reason[:60]})")


@contextmanager
def reporting(stats: Stats, spool: Spool, report: Callable[[Snapshot], None] | None
              ) -> Iterator[None]:
    """Calls ``report`` with a snapshot every REPORT_INTERVAL_S while the block runs."""
    if report is None:
        yield
        return
    done = threading.Event()
    report(stats.snapshot(time.monotonic(), *spool.size()))  # the start, for averages

    def loop() -> None:
        while not done.wait(REPORT_INTERVAL_S):
            report(stats.snapshot(time.monotonic(), *spool.size()))

    thread = threading.Thread(target=loop, name="report", daemon=True)
    thread.start()
    try:
        yield
    finally:
        done.set()
        thread.join()
        report(stats.snapshot(time.monotonic(), *spool.size()))
