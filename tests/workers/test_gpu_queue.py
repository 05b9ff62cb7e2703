"""The enhance stage goes to the gpu queue: with one worker on cpu and one on gpu, a job that
asks for enhancement runs that stage on the gpu worker and every other stage on the cpu one."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from app.core.security import create_key
from app.main import create_app
from tests.integration.services import (
    FAST_JOB,
    base_env,
    make_capture_zip,
    wait_job,
    wait_worker_ready,
    worker,
)
from workers.settings import Settings

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
        app = create_app(Settings.model_validate(values), viewer=False)
        with TestClient(app) as client:
            with app.state.gateway.sessions() as session:
                _, key = create_key(session, "tests")
            auth = {"Authorization": f"Bearer {key}"}
            wait_worker_ready(cpu)
            wait_worker_ready(gpu)
            capture = make_capture_zip(tmp_path, cameras=2, width=96, height=80)
            upload = client.post("/api/v1/captures", content=capture.read_bytes(),
                                 headers={**auth, "Content-Type": "application/zip"})
            assert upload.status_code == 201, upload.text
            response = client.post("/api/v1/jobs", headers=auth, json={
                "capture_id": upload.json()["id"], **FAST_JOB, "enhance": True,
                "enhancement": {"resolution": 64, "steps": 1}})
            assert response.status_code == 202, response.text
            job = wait_job(client, response.json()["id"], {"succeeded", "failed"}, 180)
            assert job["state"] == "succeeded", job["error"]
            report = client.get(job["links"]["report"]).json()
    finally:
        cpu.stop()
        gpu.stop()
    assert "enhance" in job["stages"] and report["enhance"]["applied"] is True
    assert report["stage_stats"]["enhance"]["mean_move_m"] > 0
    assert _stages_run(tmp_path / "gpu.log") == ["enhance"]
    assert "enhance" not in _stages_run(tmp_path / "cpu.log")
    assert "colorize" in _stages_run(tmp_path / "cpu.log")
