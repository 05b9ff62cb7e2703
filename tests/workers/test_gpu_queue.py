"""The enhance stage goes to the gpu queue: with one worker on cpu and one on gpu, a job that
asks for enhancement runs that stage on the gpu worker and every other stage on the cpu one.
The gpu worker keeps its networks between jobs."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from tests.integration.services import (
    FAST_JOB,
    base_env,
    gateway_client,
    make_capture_zip,
    stop_all,
    upload_capture,
    wait_job,
    wait_worker_ready,
    worker,
)

pytestmark = pytest.mark.slow

_STARTED = re.compile(r"job \w+ stage \d+ \((\w+)\) starting")


def _stages_run(log: Path) -> list[str]:
    return _STARTED.findall(log.read_text(errors="replace"))


def test_only_the_gpu_worker_enhances(tmp_path: Path) -> None:
    values = {"data_dir": str(tmp_path / "data")}
    env = base_env(**values)
    cpu = worker(env, tmp_path / "cpu.log", queues="cpu,validate", name="cpu").start()
    gpu = worker(env, tmp_path / "gpu.log", queues="gpu", name="gpu").start()
    try:
        with gateway_client(values) as (client, auth):
            wait_worker_ready(cpu)
            wait_worker_ready(gpu)
            capture_id = upload_capture(
                client, auth, make_capture_zip(tmp_path, cameras=2, width=96, height=80))
            jobs = []
            # The second job's enhance stage is computed again (another resolution) with the
            # networks the first loaded.
            for resolution in (64, 48):
                response = client.post("/api/v1/jobs", headers=auth, json={
                    "capture_id": capture_id, **FAST_JOB, "enhance": True,
                    "enhancement": {"resolution": resolution, "min_noise_ratio": 0.0}})
                assert response.status_code == 202, response.text
                job = wait_job(client, response.json()["id"], {"succeeded", "failed"}, 180)
                assert job["state"] == "succeeded", job["error"]
                jobs.append((job, client.get(job["links"]["report"]).json()))
    finally:
        stop_all([cpu, gpu])
    for job, report in jobs:
        assert "enhance" in job["stages"] and report["enhance"]["applied"] is True
        assert report["stage_stats"]["enhance"]["mean_offset_m"] > 0
    gpu_log = (tmp_path / "gpu.log").read_text(errors="replace")
    assert _stages_run(tmp_path / "gpu.log") == ["enhance", "enhance"]
    assert len(re.findall(r"enhance networks for regressor on \w+ loaded", gpu_log)) == 1
    assert "enhance" not in _stages_run(tmp_path / "cpu.log")
    assert "colorize" in _stages_run(tmp_path / "cpu.log")
