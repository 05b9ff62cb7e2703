"""Stage tasks in a real worker process: bad settings, bad options and the time limit each fail
the job with a message naming the cause, and the worker carries on."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import pytest
from fastapi.testclient import TestClient

from tests.integration.services import (
    FAST_JOB,
    Process,
    base_env,
    gateway_client,
    make_capture_zip,
    upload_capture,
    wait_job,
    wait_worker_ready,
    worker,
)

pytestmark = pytest.mark.slow


@dataclass
class Rig:
    client: TestClient
    auth: dict[str, str]
    capture_id: str
    worker: Process

    def run(self, **options: Any) -> dict[str, Any]:
        response = self.client.post("/api/v1/jobs", headers=self.auth,
                                    json={"capture_id": self.capture_id, **options})
        assert response.status_code == 202, response.text
        return wait_job(self.client, response.json()["id"], {"succeeded", "failed"}, 120)


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Rig]:
    folder = tmp_path_factory.mktemp("tasks")
    values = {"data_dir": str(folder / "data"), "task_soft_time_limit_s": "1",
              "task_time_limit_s": "60"}
    proc = worker(base_env(**values), folder / "worker.log").start()
    with gateway_client(values) as (client, auth):
        wait_worker_ready(proc)
        capture = make_capture_zip(folder, cameras=2, width=96, height=80)
        yield Rig(client, auth, upload_capture(client, auth, capture), proc)
    proc.stop()


def test_a_stage_setting_out_of_range_fails_the_job_with_its_name(rig: Rig) -> None:
    # Names and kinds are the gateway's to refuse (a 422); ranges are the worker's.
    job = rig.run(enhance=False, meshing={"poisson_depth": 99})
    assert job["state"] == "failed"
    assert "meshing" in job["error"] and "poisson_depth" in job["error"], job["error"]


def test_missing_frame_fails_the_job(rig: Rig) -> None:
    job = rig.run(enhance=False, frame_index=7)
    assert job["state"] == "failed" and "frame_index" in job["error"], job


def test_a_stage_over_the_time_limit_fails_the_job(rig: Rig) -> None:
    # Remeshing this capture to 2 mm edges takes minutes on any machine, so the 1 s limit
    # always cuts it short; the kernel's child process dies with the stage.
    job = rig.run(**{**FAST_JOB, "target_edge_length_m": 0.002, "remesh": {"iterations": 30}})
    assert job["state"] == "failed", job
    assert "ran longer than the 1 s limit" in job["error"], job
    assert rig.worker.alive  # the worker survives and takes the next job
    again = rig.run(enhance=False, frame_index=9)
    assert again["state"] == "failed" and "frame_index" in again["error"]
