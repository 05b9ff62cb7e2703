"""Live preview: from a frame-set's capture on the rig to a viewer's WebSocket.

Usage: .venv/bin/python benchmarks/live_preview.py [--cameras 8] [--seconds 10]
       [--preview-hz 10] [--workdir DIR]

Replays the 8-camera capture benchmarks/ingest.py makes (640x576 depth, 1280x720 colour, 30
fps; made here if --workdir lacks it) with `volumesh agent` at its frame rate against `volumesh
serve`, with a rig posing the cameras on a ring (so the agent fuses previews), while a viewer's
WebSocket client (the `websockets` library, as a browser would: key as the first message)
listens. Each preview carries the agent's wall-clock time of its frame-set's capture; the
client notes its arrival on the same clock. Prints one JSON object: updates per second, and
the latency (capture to socket) median, p95 and max, against the targets (<= 300 ms at >= 5
updates/s); also the ingest itself kept up (frame-sets stored).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from ingest import Serve  # noqa: E402

from tests.k4a_recordings import rig_recordings  # noqa: E402


def _capture(workdir: Path, cameras: int, seconds: int) -> Path:
    capture = workdir / f"capture-{cameras}"
    if not (capture / "capture.json").is_file():
        paths = sorted(workdir.glob("device*.mkv"))[:cameras]
        if len(paths) < cameras:
            paths = rig_recordings(workdir, cameras, seconds)
        subprocess.run([sys.executable, "-m", "app", "import-mkv", *map(str, paths), "--out",
                        str(capture)], cwd=ROOT, check=True, capture_output=True)
    return capture


def _ring_rig(camera_ids: list[str]) -> dict[str, Any]:
    """Poses on a 2 m ring looking at its centre, depth cameras' +z inwards, +Y up."""
    poses = {}
    for i, camera_id in enumerate(camera_ids):
        angle = 2 * np.pi * i / len(camera_ids)
        eye = np.array([2.0 * np.sin(angle), 1.0 + 0.4 * (i % 2), 2.0 * np.cos(angle)])
        forward = -eye * np.array([1.0, 0.0, 1.0])
        forward /= np.linalg.norm(forward)
        right = np.cross(forward, [0.0, 1.0, 0.0])
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        pose = np.eye(4)
        pose[:3, :3] = np.column_stack([right, down, forward])
        pose[:3, 3] = eye
        poses[camera_id] = pose.tolist()
    return {"format": "volumesh.rig/1", "name": "benchmark ring", "world_from_depth": poses}


class Listener(threading.Thread):
    """A viewer's socket: notes each preview's capture time and arrival time."""

    def __init__(self, url: str, key: str) -> None:
        super().__init__(daemon=True)
        self.url, self.key = url, key
        self.arrivals: list[tuple[float, float, int]] = []
        self.ready = threading.Event()
        self.closed = threading.Event()

    def run(self) -> None:
        from websockets.exceptions import ConnectionClosed
        from websockets.sync.client import connect

        with connect(self.url, max_size=None) as socket:
            socket.send(json.dumps({"key": self.key}))
            self.ready.set()
            try:
                for message in socket:
                    arrived = time.time()
                    if isinstance(message, str):
                        if json.loads(message).get("state") != "receiving":
                            break
                        continue
                    size = struct.unpack_from("<I", message)[0]
                    header = json.loads(message[4:4 + size])
                    self.arrivals.append((header["captured_at"], arrived, header["points"]))
            except ConnectionClosed:
                pass
        self.closed.set()


def _stream_id(client: httpx.Client, timeout_s: float) -> str:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        items = client.get("/api/v1/streams").json()["items"]
        if items:
            return str(items[0]["id"])
        time.sleep(0.01)
    raise SystemExit("the agent made no stream")


def _run(args: argparse.Namespace, capture: Path, tmp: Path) -> dict[str, Any]:
    serve = Serve(tmp / "data", tmp / "serve.log").start()
    key = (tmp / "data" / "api-key.txt").read_text().strip()
    client = httpx.Client(base_url=serve.url, timeout=10,
                          headers={"Authorization": f"Bearer {key}"})
    camera_ids = [c["id"] for c in json.loads((capture / "capture.json").read_text())["cameras"]]
    rig = client.post("/api/v1/rigs", json=_ring_rig(camera_ids[: args.cameras]))
    rig.raise_for_status()
    agent = subprocess.Popen(
        [sys.executable, "-m", "app", "agent", "--gateway", serve.url, "--key", key,
         "--source", f"capture:{capture}", "--spool", str(tmp / "spool"), "--rig",
         rig.json()["id"], "--preview-hz", str(args.preview_hz)],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    stream_id = _stream_id(client, 60)
    listener = Listener(serve.url.replace("http", "ws") + f"/api/v1/streams/{stream_id}/preview",
                        key)
    listener.start()
    _, stderr = agent.communicate(timeout=600)
    listener.closed.wait(60)
    stream = client.get(f"/api/v1/streams/{stream_id}").json()
    serve.stop()
    if agent.returncode != 0:
        raise SystemExit(f"the agent failed ({agent.returncode}): {stderr[-2000:]}")
    # The first second is left out: the socket opened while the stream had begun.
    arrivals = [a for a in listener.arrivals if a[0] > listener.arrivals[0][0] + 1.0]
    latency_ms = np.array([1000 * (arrived - captured) for captured, arrived, _ in arrivals])
    span_s = arrivals[-1][1] - arrivals[0][1]
    return {
        "previews": len(arrivals),
        "updates_per_s": round((len(arrivals) - 1) / span_s, 2),
        "latency_ms_median": round(float(np.median(latency_ms)), 1),
        "latency_ms_p95": round(float(np.percentile(latency_ms, 95)), 1),
        "latency_ms_max": round(float(latency_ms.max()), 1),
        "points_per_preview": int(np.median([n for _, _, n in arrivals])),
        "frame_sets_stored": stream["frames_received"],
        "agent_summary": stderr.strip().splitlines()[-1] if stderr.strip() else "",
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cameras", type=int, default=8)
    parser.add_argument("--seconds", type=int, default=10)
    parser.add_argument("--preview-hz", type=float, default=10.0)
    parser.add_argument("--workdir", type=Path, default=None,
                        help="keep the recordings and the capture here (reused when present)")
    args = parser.parse_args()
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="volumesh-live-bench-"))
    workdir.mkdir(parents=True, exist_ok=True)
    capture = _capture(workdir, args.cameras, args.seconds)
    tmp = Path(tempfile.mkdtemp(prefix="volumesh-live-run-"))
    load = os.getloadavg()[0]
    try:
        result = _run(args, capture, tmp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        if args.workdir is None:
            shutil.rmtree(workdir, ignore_errors=True)
    print(json.dumps({
        "cameras": args.cameras, "seconds": args.seconds, "preview_hz": args.preview_hz,
        **result, "target_latency_ms": 300, "target_updates_per_s": 5,
        "load_average_before": round(load, 2), "load_average_after": round(os.getloadavg()[0], 2),
        "cpus": os.cpu_count(), "python": platform.python_version()}, indent=1))


if __name__ == "__main__":
    main()
