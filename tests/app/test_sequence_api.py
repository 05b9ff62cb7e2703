"""POST /jobs with ``frames``: the body's checks, the range against the capture's frames, the
frame jobs made and how GET /jobs lists them (no stage runs here: the worker only validates)."""

from __future__ import annotations

from typing import Any

import pytest

from tests.app.conftest import Service


@pytest.fixture(scope="module")
def capture_id(service: Service) -> str:
    upload = service.client.post("/api/v1/captures", content=service.capture_zip.read_bytes(),
                                 headers={"Content-Type": "application/zip"})
    assert upload.status_code == 201, upload.text
    return str(upload.json()["id"])


@pytest.mark.parametrize(("frames", "extra", "says"), [
    ({"first": 3, "last": 1}, {}, "last (1) comes before first (3)"),
    ({"first": -1, "last": 0}, {}, "greater than or equal to 0"),
    ({"first": 0}, {}, "Field required"),
    ({"first": 0, "last": 0, "step": 2}, {}, "Extra inputs"),
    ("some", {}, "all"),
    ("all", {"frame_index": 0}, "give neither frame_index"),
])
def test_a_bad_frames_field_is_a_422_naming_it(service: Service, capture_id: str, frames: Any,
                                               extra: dict[str, Any], says: str) -> None:
    answer = service.client.post("/api/v1/jobs", json={"capture_id": capture_id,
                                                      "frames": frames, **extra})
    assert answer.status_code == 422, answer.text
    assert says in answer.text


def test_a_range_outside_the_capture_is_a_422_naming_it(service: Service,
                                                        capture_id: str) -> None:
    answer = service.client.post("/api/v1/jobs", json={"capture_id": capture_id,
                                                      "frames": {"first": 0, "last": 5}})
    assert answer.status_code == 422
    problem = answer.json()
    assert problem["type"].endswith("/validation-error")
    assert "0..5" in problem["detail"] and "(0..0)" in problem["detail"]
    assert "frame 5" in problem["detail"]


def test_a_sequence_makes_one_frame_job_per_frame(service: Service, capture_id: str) -> None:
    created = service.client.post("/api/v1/jobs", json={
        "capture_id": capture_id, "frames": {"first": 0, "last": 0}, "voxel_size_m": 0.01})
    assert created.status_code == 202, created.text
    sequence = created.json()
    assert (sequence["frames_total"], sequence["frames_done"], sequence["frames_failed"]) == \
        (1, 0, 0)
    assert sequence["stages"] == ["frames", "export"] and sequence["stage"] == "frames"
    assert sequence["links"]["frames"] == f"/api/v1/jobs?parent_id={sequence['id']}"
    frames = service.client.get(sequence["links"]["frames"]).json()["items"]
    assert len(frames) == 1
    frame = frames[0]
    assert (frame["parent_id"], frame["frame_index"]) == (sequence["id"], 0)
    inherited = {k: v for k, v in sequence["options"].items() if k != "frames"}
    assert frame["options"] == {**inherited, "frame_index": 0}
    assert frame["options"]["voxel_size_m"] == 0.01
    assert frame["links"]["parent"] == f"/api/v1/jobs/{sequence['id']}"
    top = {j["id"] for j in service.client.get("/api/v1/jobs?limit=100").json()["items"]}
    assert sequence["id"] in top and frame["id"] not in top
    cancelled = service.client.delete(f"/api/v1/jobs/{sequence['id']}")
    assert cancelled.json()["state"] == "cancelled"
    assert service.client.get(f"/api/v1/jobs/{frame['id']}").json()["state"] == "cancelled"


def test_cancelling_one_frame_counts_it_failed_in_its_sequence(service: Service,
                                                              capture_id: str) -> None:
    created = service.client.post("/api/v1/jobs", json={"capture_id": capture_id,
                                                        "frames": "all", "voxel_size_m": 0.02})
    sequence_id = created.json()["id"]
    frame = service.client.get(f"/api/v1/jobs?parent_id={sequence_id}").json()["items"][0]
    assert service.client.delete(f"/api/v1/jobs/{frame['id']}").status_code == 200
    sequence = service.client.get(f"/api/v1/jobs/{sequence_id}").json()
    assert (sequence["frames_done"], sequence["frames_failed"]) == (0, 1)
    assert sequence["failed_frames"] == {"0": "cancelled"}
    assert sequence["stage"] == "export"  # its last frame is over: the export is queued
    assert sequence["progress"] == 0.99
