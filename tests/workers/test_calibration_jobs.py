"""Calibration in the service, with a real worker: a job calibrates from a ChArUco capture
first and saves the rig, a later job reuses the saved rig, a job can only calibrate, and a rig
file can be uploaded and fetched back."""

from __future__ import annotations

import io
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from tests.integration.services import (
    FAST_JOB,
    Process,
    base_env,
    check_draco_glb,
    gateway_client,
    make_calibration_zip,
    make_capture_zip,
    upload_capture,
    wait_job,
    wait_worker_ready,
    worker,
)

pytestmark = pytest.mark.slow


@dataclass
class Service:
    client: TestClient
    auth: dict[str, str]
    subject_id: str
    calibration_id: str
    truth: dict[str, np.ndarray]
    worker: Process

    def run(self, **body: Any) -> dict[str, Any]:
        response = self.client.post("/api/v1/jobs", headers=self.auth, json=body)
        assert response.status_code == 202, response.text
        return wait_job(self.client, response.json()["id"], {"succeeded", "failed"}, 180)


def _capture_poses(zip_bytes: bytes) -> dict[str, np.ndarray]:
    import json

    with zipfile.ZipFile(io.BytesIO(zip_bytes)) as archive:
        name = next(n for n in archive.namelist() if n.endswith("capture.json"))
        meta = json.loads(archive.read(name))
    return {c["id"]: np.array(c["world_from_depth"]) for c in meta["cameras"]}


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Service]:
    folder = tmp_path_factory.mktemp("calibration-jobs")
    values = {"data_dir": str(folder / "data")}
    proc = worker(base_env(**values), folder / "worker.log").start()
    with gateway_client(values) as (client, auth):
        wait_worker_ready(proc)
        subject = make_capture_zip(folder, cameras=4, width=160, height=144)
        calibration = make_calibration_zip(folder, cameras=4, width=160, height=144)
        yield Service(client, auth, upload_capture(client, auth, subject),
                      upload_capture(client, auth, calibration),
                      _capture_poses(subject.read_bytes()), proc)
    proc.stop()


def _relative(poses: dict[str, Any]) -> dict[str, np.ndarray]:
    """Every camera's pose in the first camera's frame (the world frame is arbitrary)."""
    first = np.linalg.inv(np.asarray(poses["cam0"], dtype=float))
    return {c: first @ np.asarray(m, dtype=float) for c, m in poses.items()}


def test_a_job_calibrates_first_and_saves_the_rig(service: Service) -> None:
    job = service.run(capture_id=service.subject_id,
                      calibration_capture_id=service.calibration_id, rig_name="studio-a",
                      **FAST_JOB)
    assert job["state"] == "succeeded", job["error"]
    assert job["stages"][0] == "calibrate" and job["stages"][-1] == "export"
    assert job["links"]["rig"] == f"/api/v1/rigs/{job['id']}"
    rig = service.client.get(job["links"]["rig"]).json()
    assert rig["source"] == "calibration" and rig["name"] == "studio-a"
    assert rig["calibration_capture_id"] == service.calibration_id
    assert rig["cameras"] == sorted(service.truth)
    assert max(rig["report"]["reprojection_rms_px"].values()) < 1.0, rig["report"]
    found, truth = _relative(rig["world_from_depth"]), _relative(service.truth)
    for camera in truth:
        assert np.abs(found[camera][:3, 3] - truth[camera][:3, 3]).max() < 0.005, camera
    report = service.client.get(job["links"]["report"]).json()
    assert report["rig_id"] == job["id"]
    assert report["rig"]["world_from_depth"] == rig["world_from_depth"]  # the viewer's frusta
    check_draco_glb(service.client.get(job["links"]["mesh_glb"]).content)


def test_a_saved_rig_is_reused_by_a_later_job(service: Service) -> None:
    first = service.run(calibration_capture_id=service.calibration_id, rig_name="studio-b")
    listed = service.client.get("/api/v1/rigs", params={"name": "studio-b"}).json()
    assert [r["id"] for r in listed["items"]] == [first["id"]]
    rig = listed["items"][0]
    job = service.run(capture_id=service.subject_id, rig_id=rig["id"], **FAST_JOB)
    assert job["state"] == "succeeded", job["error"]
    assert "calibrate" not in job["stages"]
    assert job["options"]["world_from_depth"] == rig["world_from_depth"]
    assert job["links"]["rig"] == f"/api/v1/rigs/{rig['id']}"


def test_a_job_can_only_calibrate(service: Service) -> None:
    job = service.run(calibration_capture_id=service.calibration_id)
    assert job["state"] == "succeeded", job["error"]
    assert job["stages"] == ["calibrate"] and job["asset_id"] is None
    assert job["capture_id"] == service.calibration_id and job["progress"] == 1.0
    assert service.client.get(job["links"]["rig"]).status_code == 200


def test_a_capture_without_a_target_fails_the_calibration_with_why(service: Service) -> None:
    job = service.run(calibration_capture_id=service.subject_id)
    assert job["state"] == "failed"
    assert "target" in job["error"], job["error"]
    assert "rig" not in job["links"]  # no rig was saved
    assert service.worker.alive


def test_a_rig_file_round_trips(service: Service) -> None:
    calibrated = service.run(calibration_capture_id=service.calibration_id)
    document = service.client.get(f"/api/v1/rigs/{calibrated['id']}/rig.json").json()
    assert document["format"] == "volumesh.rig/1" and "warnings" in document
    created = service.client.post("/api/v1/rigs", headers=service.auth,
                                  json={**document, "name": "copied"})
    assert created.status_code == 201, created.text
    assert created.headers["Location"] == f"/api/v1/rigs/{created.json()['id']}"
    again = service.client.get(created.json()["links"]["rig_json"]).json()
    assert again == document
    assert created.json()["source"] == "upload"
