"""Sequence jobs end to end on the embedded broker with a real worker process: every frame of a
capture reconstructed as its own job, the manifest served and its links followed with the key
and through a share link, a bad frame failing alone, and a cancelled sequence; and a sequence
on Redis with two workers."""

from __future__ import annotations

import json
import time
import urllib.parse
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from app.web import SequenceManifest
from tests.integration.services import (
    ANONYMOUS,
    FAST_JOB,
    Process,
    Redis,
    base_env,
    check_draco_glb,
    gateway_client,
    sequence_capture_zip,
    stop_all,
    upload_capture,
    wait_for,
    wait_job,
    wait_worker_ready,
    worker,
)

pytestmark = pytest.mark.slow
FRAMES = 4
BAD_FRAME = 2


@dataclass
class Service:
    client: Any
    auth: dict[str, str]
    capture_id: str
    worker: Process

    def frames(self, job_id: str) -> list[dict[str, Any]]:
        page = self.client.get("/api/v1/jobs", params={"parent_id": job_id, "limit": 100})
        assert page.status_code == 200, page.text
        return list(page.json()["items"])


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Service]:
    folder = tmp_path_factory.mktemp("sequence")
    values = {"data_dir": str(folder / "data")}
    proc = worker(base_env(**values), folder / "worker.log").start()
    try:
        with gateway_client(values) as (client, auth):
            wait_worker_ready(proc)
            capture = sequence_capture_zip(folder, FRAMES, BAD_FRAME)
            capture_id = upload_capture(client, auth, capture)
            yield Service(client, auth, capture_id, proc)
    finally:
        proc.stop()


def test_every_frame_is_reconstructed_and_a_bad_one_fails_alone(service: Service) -> None:
    client = service.client
    created = client.post("/api/v1/jobs", json={"capture_id": service.capture_id,
                                                "frames": "all", **FAST_JOB})
    assert created.status_code == 202, created.text
    parent = created.json()
    assert (parent["frames_total"], parent["frames_done"], parent["frames_failed"]) == \
        (FRAMES, 0, 0)
    frames = service.frames(parent["id"])
    assert [f["frame_index"] for f in frames] == list(range(FRAMES))
    assert {f["parent_id"] for f in frames} == {parent["id"]}
    listed = client.get("/api/v1/jobs", params={"limit": 100}).json()["items"]
    assert [j["id"] for j in listed] == [parent["id"]]  # top-level jobs only

    done = wait_job(client, parent["id"], {"succeeded", "failed"}, 240)
    assert done["state"] == "succeeded", (done, service.worker.tail())
    assert (done["frames_done"], done["frames_failed"], done["progress"]) == (FRAMES - 1, 1, 1.0)
    assert list(done["failed_frames"]) == [str(BAD_FRAME)]
    bad = next(f for f in service.frames(parent["id"]) if f["frame_index"] == BAD_FRAME)
    assert bad["state"] == "failed" and bad["error"] == done["failed_frames"][str(BAD_FRAME)]
    assert "too few points" in bad["error"], bad["error"]  # the pipeline says why

    manifest_url = done["links"]["sequence"]
    manifest = SequenceManifest.model_validate(client.get(manifest_url).json())
    assert manifest.fps == pytest.approx(15.0, abs=0.01)
    assert len(manifest.frames) == FRAMES - 1
    lows, highs = np.array(manifest.bounds.min), np.array(manifest.bounds.max)
    assert np.all(highs - lows > 0.5)
    for frame in manifest.frames:
        url = urllib.parse.urljoin(manifest_url, frame.url)
        check_draco_glb(client.get(url).content)
    events = client.get(f"/api/v1/jobs/{parent['id']}/events")
    data = json.loads(events.text.split("data: ", 1)[1].split("\n", 1)[0])
    assert (data["frames_done"], data["frames_failed"]) == (FRAMES - 1, 1)
    _share_link_opens_the_frames(service, done["asset_id"], manifest_url, manifest)


def _share_link_opens_the_frames(service: Service, asset_id: str, manifest_url: str,
                                 manifest: SequenceManifest) -> None:
    client = service.client
    shared = client.post(f"/api/v1/assets/{asset_id}/share", json={"expires_in_s": 600})
    assert shared.status_code == 201, shared.text
    token = shared.json()["share"]
    assert shared.json()["viewer_url"].startswith("/?sequence=")
    first = urllib.parse.urljoin(manifest_url, manifest.frames[0].url)
    assert client.get(first, headers=ANONYMOUS).status_code == 401
    assert client.get(f"{manifest_url}?share={token}", headers=ANONYMOUS).status_code == 200
    opened = client.get(f"{first}?share={token}", headers=ANONYMOUS)
    assert opened.status_code == 200
    check_draco_glb(opened.content)
    # A frame's own token opens that frame, not the sequence nor its other frames.
    frame_id = manifest.frames[0].model_dump()["asset_id"]
    other = urllib.parse.urljoin(manifest_url, manifest.frames[1].url)
    frame_token = client.post(f"/api/v1/assets/{frame_id}/share", json={}).json()["share"]
    assert client.get(f"{other}?share={frame_token}", headers=ANONYMOUS).status_code == 401
    assert client.get(f"{manifest_url}?share={frame_token}",
                      headers=ANONYMOUS).status_code == 401


def test_a_range_outside_the_capture_is_refused(service: Service) -> None:
    answer = service.client.post("/api/v1/jobs", json={
        "capture_id": service.capture_id, "frames": {"first": 1, "last": 9}})
    assert answer.status_code == 422
    assert "1..9" in answer.json()["detail"] and "0..3" in answer.json()["detail"]


def test_cancelling_a_sequence_cancels_its_frames(service: Service) -> None:
    client = service.client
    created = client.post("/api/v1/jobs", json={
        "capture_id": service.capture_id, "frames": {"first": 0, "last": 1}, **FAST_JOB,
        "remesh": {"iterations": 2}})
    assert created.status_code == 202, created.text
    job_id = created.json()["id"]
    cancelled = client.delete(f"/api/v1/jobs/{job_id}")
    assert cancelled.status_code == 200 and cancelled.json()["state"] == "cancelled"
    assert {f["state"] for f in service.frames(job_id)} == {"cancelled"}
    # The worker takes the frames' tasks and leaves them: nothing restarts or succeeds.
    wait_for(lambda: job_id not in client.get("/api/v1/jobs", params={"state": "queued"}).text,
             5, "the sequence to leave the queued list")
    time.sleep(1.0)
    assert client.get(f"/api/v1/jobs/{job_id}").json()["state"] == "cancelled"
    assert {f["state"] for f in service.frames(job_id)} == {"cancelled"}


def test_a_sequence_runs_on_redis_with_two_workers(tmp_path: Path) -> None:
    redis = Redis(tmp_path / "redis").start()
    values = {"data_dir": str(tmp_path / "data"), "broker_url": redis.url}
    procs = [worker(base_env(**values), tmp_path / f"worker-{i}.log", name=f"r{i}").start()
             for i in range(2)]
    try:
        with gateway_client(values) as (client, auth):
            for proc in procs:
                wait_worker_ready(proc)
            capture_id = upload_capture(client, auth, sequence_capture_zip(tmp_path, 2))
            created = client.post("/api/v1/jobs", json={"capture_id": capture_id,
                                                        "frames": "all", **FAST_JOB})
            assert created.status_code == 202, created.text
            done = wait_job(client, created.json()["id"], {"succeeded", "failed"}, 180)
            assert done["state"] == "succeeded", (done, procs[0].tail(), procs[1].tail())
            assert (done["frames_done"], done["frames_failed"]) == (2, 0)
            manifest = SequenceManifest.model_validate(client.get(done["links"]["sequence"])
                                                       .json())
            assert [f.model_dump()["frame_index"] for f in manifest.frames] == [0, 1]
    finally:
        stop_all([*procs, redis])
