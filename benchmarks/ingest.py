"""Streaming ingest: `volumesh agent` sending an 8-camera rig to `volumesh serve` on loopback.

Usage: .venv/bin/python benchmarks/ingest.py [--source mkv|capture] [--cameras 8]
       [--seconds 10] [--fast] [--kill-gateway-s 0] [--workdir DIR]

Writes, untimed, one Azure Kinect recording per device (tests/k4a_recordings.rig_recordings:
640x576 depth with noise and holes, 1280x720 MJPG colour, 30 fps); `--source capture` replays
the same recordings imported with `volumesh import-mkv` (depth already PNG: the agent only
reads and packs files), `--source mkv` the recordings themselves (the agent compresses each
depth image). Then runs `volumesh serve` and `volumesh agent` as child processes on one machine
and prints one JSON object:

- `ingest_frame_sets_per_s`: frame-sets the gateway stored per second, first to last (at the
  source's rate by default: 30 means it kept up; `--fast`: as fast as the agent and the
  gateway go together on these cores);
- `stored` / `unique_indices` / `duplicates`: every frame-set the source made arrives once;
- `agent_cpu_ms_per_camera_frame` and `agent_core_share_per_camera_at_30fps`: the agent's CPU
  time per camera image pair, and the share of one core a camera costs it at 30 fps;
- `gateway_cpu_ms_per_frame_set` (the serve process tree: gateway and its embedded workers);
- with `--kill-gateway-s S`: the gateway is SIGKILLed a third of the way through and started
  again S seconds later (the agent spools meanwhile); the counts show what arrived.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import resource
import shutil
import signal
import sqlite3
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import httpx

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.k4a_recordings import rig_recordings  # noqa: E402

TICK_S = 0.02


def _process_tree_cpu_s(pid: int) -> float:
    """User + system CPU seconds of ``pid``'s process group members now alive (serve runs
    its gateway and embedded workers as a group)."""
    total = 0.0
    tick = os.sysconf("SC_CLK_TCK")
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[2]) == pid:  # the process group (serve starts its own session)
            total += (int(fields[11]) + int(fields[12])) / tick
    return total


class Serve:
    def __init__(self, data_dir: Path, log: Path) -> None:
        self.data_dir, self.log = data_dir, log
        with socket_port() as port:
            self.port = port
        self.proc: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self) -> Serve:
        with self.log.open("ab") as out:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "app", "serve", "--port", str(self.port), "--data-dir",
                 str(self.data_dir)], cwd=ROOT, stdout=out, stderr=subprocess.STDOUT,
                start_new_session=True)
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            try:
                if httpx.get(self.url + "/readyz", timeout=1).status_code == 200:
                    return self
            except httpx.HTTPError:
                pass
            time.sleep(0.2)
        raise SystemExit(f"serve did not start: see {self.log}")

    def cpu_s(self) -> float:
        assert self.proc is not None
        return _process_tree_cpu_s(self.proc.pid)

    def kill(self) -> None:
        assert self.proc is not None
        os.killpg(self.proc.pid, signal.SIGKILL)
        self.proc.wait()

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)


class socket_port:  # noqa: N801 - a context manager read as a phrase
    def __enter__(self) -> int:
        import socket

        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        return int(self.sock.getsockname()[1])

    def __exit__(self, *_: Any) -> None:
        self.sock.close()


class Watcher(threading.Thread):
    """Polls the stream's stored count; notes when each count was first seen.

    It reads the job store (SQLite, WAL: a reader never holds up the gateway's writes) rather
    than asking the gateway: a GET every tick cost the gateway ~5 ms of CPU, about a third of
    what was reported as its cost per frame-set."""

    def __init__(self, url: str, key: str, database: Path) -> None:
        super().__init__(daemon=True)
        self.client = httpx.Client(base_url=url, timeout=2,
                                   headers={"Authorization": f"Bearer {key}"})
        self.database = database
        self.seen: list[tuple[float, int]] = []
        self.stream_id: str | None = None
        self.done = threading.Event()

    def run(self) -> None:
        while not self.done.is_set():
            # The gateway may be down or starting: the next tick asks again.
            with contextlib.suppress(sqlite3.Error):
                self._poll()
            time.sleep(TICK_S)

    def _poll(self) -> None:
        with contextlib.closing(sqlite3.connect(f"file:{self.database}?mode=ro", uri=True,
                                                timeout=2)) as db:
            if self.stream_id is None:
                row = db.execute("SELECT id FROM streams ORDER BY created_at DESC").fetchone()
                if row is None:
                    return
                self.stream_id = str(row[0])
            row = db.execute("SELECT frames_received FROM streams WHERE id = ?",
                             (self.stream_id,)).fetchone()
        received = int(row[0] or 0)
        if not self.seen or received != self.seen[-1][1]:
            self.seen.append((time.monotonic(), received))


def _source(args: argparse.Namespace, workdir: Path) -> str:
    paths = sorted(workdir.glob("device*.mkv"))[: args.cameras]
    if len(paths) < args.cameras:
        paths = rig_recordings(workdir, args.cameras, args.seconds)
    if args.source == "mkv":
        return "mkv:" + ",".join(map(str, paths))
    capture = workdir / f"capture-{args.cameras}"
    if not (capture / "capture.json").is_file():
        subprocess.run([sys.executable, "-m", "app", "import-mkv", *map(str, paths), "--out",
                        str(capture)], cwd=ROOT, check=True, capture_output=True)
    return f"capture:{capture}"


def _database(data_dir: Path) -> Path:
    """The job store's SQLite file that serve keeps in ``data_dir``."""
    from sqlalchemy.engine import make_url

    from workers.settings import Settings

    database = make_url(Settings(data_dir=data_dir).resolved_database_url).database
    assert database, "the benchmark's job store is SQLite"
    return Path(database)


def _count_chunks_and_frames(data_dir: Path, stream: dict[str, Any]) -> dict[str, int]:
    """What the job store holds for the stream: its count and the distinct indices stored."""
    from sqlalchemy import func, select

    from workers.db import make_engine, make_sessionmaker
    from workers.models import StreamFrame
    from workers.settings import Settings

    engine = make_engine(Settings(data_dir=data_dir))
    try:
        with make_sessionmaker(engine)() as session:
            rows = session.scalar(select(func.count()).select_from(StreamFrame)
                                  .where(StreamFrame.stream_id == stream["id"]))
            unique = session.scalar(select(func.count(func.distinct(StreamFrame.frame_index)))
                                    .where(StreamFrame.stream_id == stream["id"]))
    finally:
        engine.dispose()
    return {"stored": int(stream["frames_received"]), "rows": int(rows or 0),
            "unique_indices": int(unique or 0)}


def _run(args: argparse.Namespace, source: str, tmp: Path) -> dict[str, Any]:
    serve = Serve(tmp / "data", tmp / "serve.log").start()
    key = (tmp / "data" / "api-key.txt").read_text().strip()
    watcher = Watcher(serve.url, key, _database(tmp / "data"))
    watcher.start()
    command = [sys.executable, "-m", "app", "agent", "--gateway", serve.url, "--key", key,
               "--source", source, "--spool", str(tmp / "spool"), "--preview-hz", "0"]
    if args.fast:
        command.append("--fast")
    gateway_cpu_before = serve.cpu_s()
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    started = time.monotonic()
    agent = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True)
    gateway_cpu_s = 0.0
    if args.kill_gateway_s:
        time.sleep(args.seconds / 3)
        gateway_cpu_s += serve.cpu_s() - gateway_cpu_before
        serve.kill()
        time.sleep(args.kill_gateway_s)
        serve.start()
        gateway_cpu_before = serve.cpu_s()
    total = args.seconds * 30
    while not (watcher.seen and watcher.seen[-1][1] >= total) and agent.poll() is None:
        time.sleep(TICK_S)
    gateway_cpu_s += serve.cpu_s() - gateway_cpu_before  # before the assembly at the close
    stdout, stderr = agent.communicate(timeout=600)
    wall_s = time.monotonic() - started
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    agent_cpu_s = (usage.ru_utime + usage.ru_stime) - (before.ru_utime + before.ru_stime)
    watcher.done.set()
    stream = watcher.client.get(f"/api/v1/streams/{watcher.stream_id}").json()
    serve.stop()
    if agent.returncode != 0:
        raise SystemExit(f"the agent failed ({agent.returncode}): {stderr[-2000:]}")
    counts = _count_chunks_and_frames(tmp / "data", stream)
    first = next(t for t, n in watcher.seen if n > 0)
    last = next(t for t, n in watcher.seen if n >= total)
    images = total * args.cameras
    return {
        **counts, "expected": total, "duplicates": counts["rows"] - counts["unique_indices"],
        "capture_frames": stream.get("frames_received"), "stream_state": stream["state"],
        "ingest_frame_sets_per_s": round((total - 1) / max(last - first, 1e-9), 1),
        "agent_wall_s": round(wall_s, 1),
        "agent_cpu_s": round(agent_cpu_s, 2),
        "agent_cpu_ms_per_camera_frame": round(1000 * agent_cpu_s / images, 2),
        "agent_core_share_per_camera_at_30fps": round(30 * agent_cpu_s / images, 3),
        "gateway_cpu_ms_per_frame_set": round(1000 * gateway_cpu_s / total, 2),
        "agent_summary": stderr.strip().splitlines()[-1] if stderr.strip() else "",
        "agent_result": stdout.strip().splitlines()[0] if stdout.strip() else "",
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--source", choices=("mkv", "capture"), default="mkv")
    parser.add_argument("--cameras", type=int, default=8)
    parser.add_argument("--seconds", type=int, default=10)
    parser.add_argument("--fast", action="store_true", help="replay as fast as possible")
    parser.add_argument("--kill-gateway-s", type=float, default=0.0)
    parser.add_argument("--workdir", type=Path, default=None,
                        help="keep the recordings here (reused when present)")
    args = parser.parse_args()
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="volumesh-ingest-bench-"))
    workdir.mkdir(parents=True, exist_ok=True)
    source = _source(args, workdir)
    tmp = Path(tempfile.mkdtemp(prefix="volumesh-ingest-run-"))
    load = os.getloadavg()[0]
    try:
        result = _run(args, source, tmp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        if args.workdir is None:
            shutil.rmtree(workdir, ignore_errors=True)
    print(json.dumps({
        "source": args.source, "cameras": args.cameras, "seconds": args.seconds,
        "fast": args.fast, "kill_gateway_s": args.kill_gateway_s, **result,
        "target_frame_sets_per_s": 30, "load_average_before": round(load, 2),
        "load_average_after": round(os.getloadavg()[0], 2), "cpus": os.cpu_count(),
        "python": platform.python_version()}, indent=1))


if __name__ == "__main__":
    main()
