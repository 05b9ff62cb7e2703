"""Capture upload throughput on loopback, and the gateway's peak memory against upload size.

Targets: >= 100 MB/s; peak gateway memory independent of the upload's size (the body is
streamed to disk). Each upload is a real capture (2 small cameras) padded with a large extra
file, so it is received, hashed, zip-checked, stored and validated by a worker: 201.
    .venv/bin/python benchmarks/api_upload.py [--sizes-mb 64,256,1024]
Prints one JSON object.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import socket
import sys
import tempfile
import time
import zipfile
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.api_common import (  # noqa: E402
    free_port,
    gateway_cmd,
    peak_rss_mb,
    process,
    rss_mb,
    service_env,
    wait_http,
    worker_cmd,
)

BLOCK = 1024 * 1024


def _small_capture_entries() -> dict[str, bytes]:
    from pipeline.io.capture_io import write_capture, zip_capture
    from pipeline.synth.rig import RigConfig
    from pipeline.synth.scene import SynthConfig, sample_mesh, synthesize

    meta, views, _ = synthesize(sample_mesh(), SynthConfig(
        camera_count=2, rig=RigConfig(width=64, height=48)))
    with tempfile.TemporaryDirectory() as tmp:
        write_capture(Path(tmp) / "c", meta, views)
        zip_capture(Path(tmp) / "c", Path(tmp) / "c.zip")
        with zipfile.ZipFile(Path(tmp) / "c.zip") as archive:
            return {n: archive.read(n) for n in archive.namelist()}


def _padded_zip(path: Path, entries: dict[str, bytes], size_mb: int) -> None:
    """The capture plus extra/pad.bin of ``size_mb`` MiB of random (incompressible) bytes."""
    block = os.urandom(BLOCK)
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as archive:
        for name, data in entries.items():
            archive.writestr(name, data)
        with archive.open("extra/pad.bin", "w", force_zip64=True) as pad:
            pad.write(os.urandom(64))  # unique content per file: no deduplication
            for _ in range(size_mb):
                pad.write(block)


def _upload(port: int, path: Path, key: str) -> tuple[float, float, int, bytes]:
    """POST the file with sendfile: (seconds until the gateway took the last byte, seconds to
    the whole response, status, body)."""
    size = path.stat().st_size
    head = (f"POST /api/v1/captures HTTP/1.1\r\nHost: bench\r\nContent-Type: application/zip\r\n"
            f"Content-Length: {size}\r\nAuthorization: Bearer {key}\r\n"
            "Connection: close\r\n\r\n").encode()
    with socket.create_connection(("127.0.0.1", port)) as sock, path.open("rb") as body:
        started = time.perf_counter()
        sock.sendall(head)
        sock.sendfile(body)
        sent = time.perf_counter() - started  # the socket buffers hold only a few MB
        response = io.BytesIO()
        while chunk := sock.recv(65536):
            response.write(chunk)
        seconds = time.perf_counter() - started
    raw = response.getvalue()
    return sent, seconds, int(raw[9:12]), raw.split(b"\r\n\r\n", 1)[-1]


def _wait_ready(log: Path, timeout_s: float = 60) -> None:
    deadline = time.monotonic() + timeout_s
    while " ready." not in log.read_text(errors="replace"):
        if time.monotonic() > deadline:
            raise TimeoutError(f"worker not ready: {log}")
        time.sleep(0.1)


def _make_key(settings: dict[str, str]) -> str:
    from app.core.security import create_key
    from workers.db import init_db, make_engine, make_sessionmaker
    from workers.settings import Settings

    engine = make_engine(Settings.model_validate(settings))
    init_db(engine)
    with make_sessionmaker(engine)() as session:
        _, key = create_key(session, "bench")
    engine.dispose()
    return key


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--sizes-mb", default="64,256,1024")
    args = parser.parse_args()
    sizes = [int(s) for s in args.sizes_mb.split(",")]
    entries = _small_capture_entries()
    runs: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        settings = {"data_dir": str(Path(tmp) / "data"),
                    "max_upload_bytes": str(8 * 1024**3)}
        key = _make_key(settings)
        env = service_env(**settings)
        port = free_port()
        with process(worker_cmd("validate"), env, Path(tmp) / "worker.log"), \
                process(gateway_cmd(port, 1), env, Path(tmp) / "gateway.log") as gateway:
            wait_http(port)
            _wait_ready(Path(tmp) / "worker.log")
            baseline = rss_mb(gateway.pid)
            for size_mb in [1, *sizes]:  # 1 MiB first: warms the worker, not reported
                zip_path = Path(tmp) / f"upload-{size_mb}.zip"
                _padded_zip(zip_path, entries, size_mb)
                sent, seconds, status, body = _upload(port, zip_path, key)
                total = zip_path.stat().st_size
                runs.append({"size_mb": round(total / 1e6, 1), "status": status,
                             "streamed_s": round(sent, 3),
                             "streamed_mb_per_s": round(total / 1e6 / sent, 1),
                             "to_201_s": round(seconds, 3),
                             "mb_per_s": round(total / 1e6 / seconds, 1),
                             "gateway_peak_rss_mb": round(peak_rss_mb(gateway.pid), 1)})
                if status != 201:
                    runs[-1]["body"] = body[:300].decode(errors="replace")
                zip_path.unlink()
    runs = runs[1:]
    peaks = [r["gateway_peak_rss_mb"] for r in runs]
    result: dict[str, Any] = {
        "benchmark": "POST /api/v1/captures (raw application/zip body, loopback)",
        "gateway_baseline_rss_mb": round(baseline, 1),
        "runs": runs,
        "min_mb_per_s": min(r["mb_per_s"] for r in runs),
        "note": "mb_per_s is to the 201 (received, hashed, checked, stored, read by a worker)",
        "peak_rss_growth_mb": round(max(peaks) - min(peaks), 1),
        "target": {"mb_per_s": 100, "memory": "peak independent of size"},
    }
    result["meets_target"] = (all(r["status"] == 201 for r in runs)
                              and result["min_mb_per_s"] >= 100
                              and result["peak_rss_growth_mb"] < 20)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
