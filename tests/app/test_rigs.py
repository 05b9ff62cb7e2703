"""/rigs and the rig options of POST /jobs: what is refused, and with which message."""

from __future__ import annotations

import math
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from app.core.poses import check_rigid
from tests.app.conftest import Service
from tests.integration.services import ANONYMOUS


def _pose(yaw_deg: float = 30.0, x_m: float = 1.0) -> list[list[float]]:
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    return [[c, 0.0, s, x_m], [0.0, 1.0, 0.0, 1.2], [-s, 0.0, c, -2.0], [0.0, 0.0, 0.0, 1.0]]


def _problem(response: Any, status: int) -> dict[str, Any]:
    assert response.status_code == status, response.text
    assert response.headers["content-type"].startswith("application/problem+json")
    body: dict[str, Any] = response.json()
    return body


def test_a_rig_file_is_saved_listed_and_fetched(service: Service) -> None:
    document = {"format": "volumesh.rig/1", "world_from_depth": {"cam0": _pose(0, 0),
                                                                 "cam1": _pose(90, 2)},
                "reprojection_rms_px": {"cam0": 0.2, "cam1": 0.3}, "warnings": []}
    created = service.client.post("/api/v1/rigs", headers=service.auth,
                                  json={**document, "name": "lab"})
    assert created.status_code == 201, created.text
    rig = created.json()
    assert rig["cameras"] == ["cam0", "cam1"] and rig["source"] == "upload"
    assert rig["report"] == {"reprojection_rms_px": {"cam0": 0.2, "cam1": 0.3}, "warnings": []}
    assert service.client.get(rig["links"]["rig_json"]).json() == document
    listed = service.client.get("/api/v1/rigs", params={"name": "lab"}).json()
    assert rig["id"] in [r["id"] for r in listed["items"]]


@pytest.mark.parametrize(("matrix", "why"), [
    ([[1, 0, 0], [0, 1, 0], [0, 0, 1]], "4x4"),
    ([[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "not rigid"),
    ([[-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "reflection"),
    ([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]], "last row"),
])
def test_a_bad_pose_is_refused_naming_the_camera(service: Service, matrix: Any,
                                                 why: str) -> None:
    response = service.client.post("/api/v1/rigs", headers=service.auth,
                                   json={"world_from_depth": {"cam0": _pose(), "cam3": matrix}})
    problem = _problem(response, 422)
    assert "world_from_depth.cam3" in problem["detail"] and why in problem["detail"], problem


def test_a_rig_needs_a_key_known_format_and_poses(service: Service) -> None:
    body = {"world_from_depth": {"cam0": _pose()}}
    _problem(service.client.post("/api/v1/rigs", json=body, headers=ANONYMOUS), 401)
    problem = _problem(service.client.post("/api/v1/rigs", headers=service.auth,
                                           json={**body, "format": "other/2"}), 422)
    assert "format" in problem["detail"]
    problem = _problem(service.client.post("/api/v1/rigs", headers=service.auth,
                                           json={"world_from_depth": {}}), 422)
    assert "world_from_depth" in problem["detail"]
    problem = _problem(service.client.post("/api/v1/rigs", headers=service.auth,
                                           json={"world_from_depth": {"../x": _pose()}}), 422)
    assert "camera id" in problem["detail"]
    _problem(service.client.get("/api/v1/rigs/" + "0" * 32), 404)


def test_jobs_take_one_source_of_poses(service: Service) -> None:
    some_id = "a" * 32
    cases = [
        ({"capture_id": some_id, "rig_id": some_id, "calibration_capture_id": some_id},
         "at most one of"),
        ({"capture_id": some_id, "rig_id": some_id,
          "world_from_depth": {"cam0": _pose()}}, "at most one of"),
        ({}, "capture_id is required"),
        ({"capture_id": some_id, "rig_name": "x"}, "need calibration_capture_id"),
        ({"capture_id": some_id, "world_from_depth": {"cam0": [[1.0] * 4] * 4}},
         "world_from_depth.cam0"),
    ]
    for body, why in cases:
        problem = _problem(service.client.post("/api/v1/jobs", headers=service.auth,
                                               json=body), 422)
        assert why in problem["detail"], (body, problem)


def test_jobs_name_a_missing_rig_or_calibration_capture(service: Service) -> None:
    upload = service.client.post("/api/v1/captures", content=service.capture_zip.read_bytes(),
                                 headers={**service.auth, "Content-Type": "application/zip"})
    capture_id = upload.json()["id"]
    missing = "b" * 32
    problem = _problem(service.client.post("/api/v1/jobs", headers=service.auth, json={
        "capture_id": capture_id, "rig_id": missing}), 404)
    assert f"no rig {missing}" in problem["detail"]
    problem = _problem(service.client.post("/api/v1/jobs", headers=service.auth, json={
        "capture_id": capture_id, "calibration_capture_id": missing}), 404)
    assert f"no capture {missing}" in problem["detail"]


_angles = st.floats(-math.pi, math.pi, allow_nan=False)


@settings(max_examples=60, deadline=None)
@given(_angles, _angles, _angles, st.lists(st.floats(-10, 10), min_size=3, max_size=3))
def test_check_rigid_accepts_every_rotation(a: float, b: float, c: float,
                                            t: list[float]) -> None:
    import numpy as np
    from scipy.spatial.transform import Rotation

    matrix = np.eye(4)
    matrix[:3, :3] = Rotation.from_euler("xyz", [a, b, c]).as_matrix()
    matrix[:3, 3] = t
    assert check_rigid(matrix.tolist(), "pose") == matrix.tolist()
    flipped = matrix.copy()
    flipped[:3, 0] *= -1
    with pytest.raises(ValueError, match="reflection"):
        check_rigid(flipped.tolist(), "pose")
