"""Leases and worker presence with real processes: the stage worker of `volumesh serve` SIGKILLed
mid-stage while serve runs on (its stage is queued again once its lease lapses, and no stage's
output is computed twice), and a gateway with no worker (a job says why it waits, /readyz
names the queues nobody consumes, until a worker starts)."""

from __future__ import annotations

import os
import signal
import sys
import time
from pathlib import Path
from typing import Any

import httpx
import pytest

from tests.integration.services import (
    FAST_JOB,
    Gateway,
    Process,
    base_env,
    create_key,
    free_port,
    make_capture_zip,
    stop_all,
    wait_for,
    wait_job,
    wait_worker_ready,
    worker,
)
from tests.integration.stage_logs import check_stages_ran_once, requeued

pytestmark = pytest.mark.slow
LEASE_S = 3.0
"""A short lease, so a dead worker's stage is queued again within seconds."""


def running_stage(client: httpx.Client, job_id: str, stages: set[str]) -> dict[str, Any]:
    """Wait until the job runs one of ``stages``; fail at once if it ends first."""
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        job = dict(client.get(f"/api/v1/jobs/{job_id}").json())
        assert job["state"] in ("queued", "running"), f"job ended early: {job}"
        if job["state"] == "running" and job["stage"] in stages:
            return job
        time.sleep(0.02)
    raise TimeoutError(f"job {job_id} never ran {stages}")


def _stage_worker_pid(data_dir: Path) -> int:
    """The embedded stage worker's pid, as the worker recorded itself in the job store."""
    from workers.db import make_engine, make_sessionmaker
    from workers.presence import live_workers
    from workers.settings import Settings

    engine = make_engine(Settings(data_dir=data_dir))
    try:
        rows = live_workers(make_sessionmaker(engine), heartbeat_s=5.0)
    finally:
        engine.dispose()
    pids = [row.pid for row in rows if row.hostname.startswith("embedded-stages")]
    assert len(pids) == 1, [(row.hostname, row.pid) for row in rows]
    return pids[0]


def test_a_killed_embedded_worker_loses_nothing(tmp_path: Path) -> None:
    data_dir = tmp_path / "data"
    port = free_port()
    serve = Process([sys.executable, "-m", "app", "serve", "--port", str(port), "--data-dir",
                     str(data_dir)], base_env(stage_lease_s=str(LEASE_S)),
                    tmp_path / "serve.log").start()
    client = httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=60)
    try:
        wait_for(lambda: client.get("/readyz").status_code == 200, 90,
                 f"serve and its workers to be ready\n{serve.tail()}", interval_s=0.2)
        client.headers["Authorization"] = f"Bearer {(data_dir / 'api-key.txt').read_text().strip()}"
        capture = make_capture_zip(tmp_path, cameras=4, width=160, height=144)
        upload = client.post("/api/v1/captures", content=capture.read_bytes(),
                             headers={"Content-Type": "application/zip"})
        assert upload.status_code == 201, upload.text
        job = client.post("/api/v1/jobs", json={"capture_id": upload.json()["id"], **FAST_JOB})
        assert job.status_code == 202, job.text
        job_id = job.json()["id"]
        running_stage(client, job_id, {"mesh", "remesh"})
        pid = _stage_worker_pid(data_dir)
        os.killpg(pid, signal.SIGKILL)  # the worker and its pool process, mid-stage
        killed_at = time.monotonic()
        found = wait_for(lambda: requeued(serve.log.read_text(errors="replace"), job_id), 60,
                         f"the gateway to queue the stage again\n{serve.tail()}")
        print(f"embedded: stage {found[0]} queued again "
              f"{time.monotonic() - killed_at:.1f} s after the SIGKILL")
        done = wait_job(client, job_id, {"succeeded", "failed"}, 120 - (time.monotonic() -
                                                                         killed_at))
        assert done["state"] == "succeeded", (done, serve.tail())
        assert "embedded worker stages exited (-9); restarting it" in serve.log.read_text()
        assert found == [found[0]] and done["stages"][found[0][0]] == found[0][1]
        check_stages_ran_once(serve.log.read_text(errors="replace"), done, found[0][0])
    finally:
        client.close()
        # Nothing more to see: SIGKILL, its workers get their SIGTERM from the kernel
        # (PR_SET_PDEATHSIG); a graceful stop takes seconds and is test_embedded.py's to check.
        serve.kill()


def _readiness(client: httpx.Client) -> tuple[int, dict[str, str]]:
    response = client.get("/readyz")
    return response.status_code, dict(response.json()["checks"])


def test_a_job_says_why_it_waits_for_a_worker(tmp_path: Path) -> None:
    env = base_env(data_dir=str(tmp_path / "data"), worker_heartbeat_s="1")
    gateway = Gateway(env, tmp_path / "gateway.log").start()
    client = httpx.Client(base_url=gateway.url, timeout=60,
                          headers={"Authorization": f"Bearer {create_key(env)}"})
    procs: list[Process] = [gateway]
    try:
        status, checks = _readiness(client)
        assert status == 503 and checks["queues"] == "no live worker consumes cpu, gpu, validate"
        assert checks["database"] == checks["broker"] == checks["storage"] == "ok"

        validator = worker(env, tmp_path / "validator.log", queues="validate", name="v")
        procs.append(validator.start())
        wait_worker_ready(validator)
        wait_for(lambda: _readiness(client)[1]["queues"] == "no live worker consumes cpu, gpu",
                 10, "readyz to see the validator")
        capture = make_capture_zip(tmp_path, cameras=4, width=160, height=144)
        upload = client.post("/api/v1/captures", content=capture.read_bytes(),
                             headers={"Content-Type": "application/zip"})
        assert upload.status_code == 201, upload.text

        created = client.post("/api/v1/jobs", json={"capture_id": upload.json()["id"],
                                                    **FAST_JOB})
        reason = ("no worker consumes the 'cpu' queue; start one with "
                  "`volumesh worker --queues cpu`")
        assert created.status_code == 202, created.text
        assert (created.json()["state"], created.json()["waiting_reason"]) == ("queued", reason)
        job_id = created.json()["id"]
        time.sleep(1.0)
        got = client.get(f"/api/v1/jobs/{job_id}").json()
        assert (got["state"], got["waiting_reason"]) == ("queued", reason)
        listed = client.get("/api/v1/jobs").json()["items"]
        assert [(j["id"], j["waiting_reason"]) for j in listed] == [(job_id, reason)]

        stages = worker(env, tmp_path / "stages.log", queues="cpu,gpu", name="s")
        procs.append(stages.start())
        wait_worker_ready(stages)
        wait_for(lambda: _readiness(client) == (200, {"database": "ok", "storage": "ok",
                                                      "broker": "ok", "queues": "ok"}),
                 10, "readyz to be ok")
        done = wait_job(client, job_id, {"succeeded", "failed"}, 120)
        assert done["state"] == "succeeded" and done["waiting_reason"] is None, done

        stages.stop(grace_s=20.0)  # a clean stop takes the worker off the list at once
        wait_for(lambda: _readiness(client)[1]["queues"] == "no live worker consumes cpu, gpu",
                 10, "readyz to miss the stopped worker")
    finally:
        client.close()
        stop_all(procs)
