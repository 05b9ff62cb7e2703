"""GET /api/v1/jobs/{id} under load: requests/s and latency with 50 concurrent clients, each
request with its API key (checked, and the job's owner compared, on every request).

Target: >= 500 requests/s with p99 <= 50 ms on two cores. Two runs: the clients back to back
(the most the gateway serves; latency is then set by queueing, concurrency / throughput), and the
same clients paced together at the target rate (the latency a client sees at that load, counted
from each request's scheduled time). The target is judged on the paced run.
    .venv/bin/python benchmarks/api_jobs.py [--workers 2] [--clients 50] [--seconds 10]
Prints one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.api_common import (  # noqa: E402
    cpu_seconds,
    free_port,
    gateway_cmd,
    load,
    load_average,
    percentile,
    process,
    process_tree,
    service_env,
    wait_http,
)


def _seed_job(settings: dict[str, str]) -> tuple[str, str]:
    """A key, and a capture and a running job of its owner in the store, as a worker would
    leave them mid-job; returns (job id, key)."""
    from app.core.security import create_key, owner_of
    from workers.db import init_db, make_engine, make_sessionmaker
    from workers.models import Capture, Job
    from workers.settings import Settings

    engine = make_engine(Settings.model_validate(settings))
    init_db(engine)
    with make_sessionmaker(engine)() as session:
        row, key = create_key(session, "bench")
    with make_sessionmaker(engine).begin() as session:
        session.add(Capture(id="c" * 32, sha256="c" * 64, size_bytes=1, storage_key="k",
                            state="ready", cameras=8, frames=1))
        session.add(Job(id="a" * 32, capture_id="c" * 32, owner=owner_of(row.id, None),
                        state="running", stage="mesh",
                        stage_index=4, done_count=4, progress=0.55,
                        stages=["filter", "align", "register", "refine", "mesh", "remesh",
                                "colorize", "export"],
                        stage_timings={"filter": 0.5, "align": 0.4, "register": 0.9,
                                       "refine": 0.3}, options={"enhance": False}))
    engine.dispose()
    return "a" * 32, key


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--workers", type=int, default=2, help="uvicorn processes")
    parser.add_argument("--clients", type=int, default=50)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--rate", type=float, default=500.0, help="paced run, requests/s")
    parser.add_argument("--database-url", default=None, help="default: SQLite in a temp dir")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        settings = {"data_dir": tmp}
        if args.database_url:
            settings["database_url"] = args.database_url
        job_id, key = _seed_job(settings)
        port = free_port()
        with process(gateway_cmd(port, args.workers), service_env(**settings),
                     Path(tmp) / "gateway.log") as gateway:
            wait_http(port)
            path = f"/api/v1/jobs/{job_id}"
            load(port, path, key, args.clients, 2.0)  # warm-up: connections, caches
            pids = process_tree(gateway.pid)
            load_before, cpu_before = load_average(), cpu_seconds(pids)
            started = time.perf_counter()
            latencies, statuses = load(port, path, key, args.clients, args.seconds)
            elapsed = time.perf_counter() - started
            cpu_used = cpu_seconds(pids) - cpu_before
            paced_started = time.perf_counter()
            paced, paced_statuses = load(port, path, key, args.clients, args.seconds,
                                         args.rate)
            paced_elapsed = time.perf_counter() - paced_started
    result = {
        "benchmark": "GET /api/v1/jobs/{id}",
        "clients": args.clients,
        "gateway_processes": args.workers,
        "database": "postgresql" if args.database_url else "sqlite",
        "seconds": round(elapsed, 2),
        "requests": len(latencies),
        "requests_per_s": round(len(latencies) / elapsed, 1),
        "p50_ms": round(percentile(latencies, 0.50) * 1e3, 2),
        "p99_ms": round(percentile(latencies, 0.99) * 1e3, 2),
        "max_ms": round(max(latencies) * 1e3, 2) if latencies else None,
        "statuses": statuses,
        "gateway_cpu_ms_per_request": round(cpu_used / max(len(latencies), 1) * 1e3, 3),
        "gateway_cpu_share": round(cpu_used / elapsed, 2),
        "load_average_1min": [load_before, load_average()],
        "cores": os.cpu_count(),
        "paced": {
            "rate_asked_per_s": args.rate,
            "requests_per_s": round(len(paced) / paced_elapsed, 1),
            "p50_ms": round(percentile(paced, 0.50) * 1e3, 2),
            "p99_ms": round(percentile(paced, 0.99) * 1e3, 2),
            "max_ms": round(max(paced) * 1e3, 2) if paced else None,
            "statuses": paced_statuses,
        },
        "target": {"requests_per_s": 500, "p99_ms": 50},
    }
    paced_result = result["paced"]
    result["meets_target"] = (paced_result["requests_per_s"] >= 0.98 * 500
                              and paced_result["p99_ms"] <= 50
                              and set(statuses) == set(paced_statuses) == {200})
    print(json.dumps(result))


if __name__ == "__main__":
    main()
