"""The scaled-out service: gateway alone, Celery workers on a real Redis, job store in a fresh
PostgreSQL database (SQLite where none runs) and captures on an S3-compatible server.

Faults: a worker SIGKILLed mid-job (its stage's lease lapses and the gateway queues it again,
long before Redis's visibility timeout), Redis restarted mid-job, a job cancelled while running.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import pytest

from tests.integration.services import (
    FAST_JOB,
    Gateway,
    MotoS3,
    Process,
    Redis,
    base_env,
    check_draco_glb,
    create_key,
    fresh_postgres_db,
    make_capture_zip,
    postgres_available,
    stop_all,
    wait_for,
    wait_job,
    wait_worker_ready,
    worker,
)
from tests.integration.stage_logs import check_stages_ran_once, requeued

pytestmark = pytest.mark.slow
LEASE_S = 3.0
"""A short stage lease: a killed worker's stage is queued again within seconds."""
SETTLE_S = 8.0


@dataclass
class Cluster:
    folder: Path
    env: dict[str, str]
    redis: Redis
    gateway: Gateway
    workers: list[Process]
    client: httpx.Client
    key: str
    capture_id: str
    names: list[str] = field(default_factory=list)

    @property
    def auth(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.key}"}

    def add_worker(self, name: str) -> Process:
        proc = worker(self.env, self.folder / f"worker-{name}.log", name=name).start()
        self.workers.append(proc)
        wait_worker_ready(proc)
        return proc

    def submit(self, **options: Any) -> dict[str, Any]:
        body = {"capture_id": self.capture_id, **FAST_JOB, **options}
        response = self.client.post("/api/v1/jobs", json=body, headers=self.auth)
        assert response.status_code == 202, response.text
        return dict(response.json())

    def running_stage(self, job_id: str, stages: set[str]) -> dict[str, Any]:
        """Wait until the job runs one of ``stages``; fails at once if the job ends first."""
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            job = dict(self.client.get(f"/api/v1/jobs/{job_id}").json())
            assert job["state"] in ("queued", "running"), f"job ended early: {job}"
            if job["state"] == "running" and job["stage"] in stages:
                return job
            time.sleep(0.02)
        raise TimeoutError(f"job {job_id} never ran {stages}")

    def worker_running(self, job: dict[str, Any]) -> Process:
        """The worker whose log shows it started the job's current stage."""
        index = job["stages"].index(job["stage"])
        line = f"job {job['id']} stage {index} ({job['stage']}) starting"
        return wait_for(lambda: next((w for w in self.workers if w.alive and
                                      line in w.log.read_text(errors="replace")), None),
                        10, f"a worker log with {line!r}")


@pytest.fixture(scope="module")
def cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cluster]:
    folder = tmp_path_factory.mktemp("cluster")
    redis = Redis(folder / "redis").start()
    moto = MotoS3(folder).start()
    moto.make_bucket("volumesh")
    with _database() as database_url:
        settings = {"data_dir": str(folder / "data"), "broker_url": redis.url,
                    "stage_lease_s": str(LEASE_S), "task_max_retries": "8",
                    **moto.settings("volumesh")}
        if database_url:
            settings["database_url"] = database_url
        env = base_env(**settings)
        gateway = Gateway(env, folder / "gateway.log").start()
        # The workers start while the key and the capture are made.
        starting = [worker(env, folder / f"worker-{name}.log", name=name).start()
                    for name in ("w1", "w2")]
        key = create_key(env)
        client = httpx.Client(base_url=gateway.url, timeout=60,
                              headers={"Authorization": f"Bearer {key}"})
        cluster = Cluster(folder, env, redis, gateway, starting, client, key, "")
        capture = make_capture_zip(folder, cameras=4, width=160, height=144)
        for proc in starting:
            wait_worker_ready(proc)
        response = client.post("/api/v1/captures", content=capture.read_bytes(),
                               headers={**cluster.auth, "Content-Type": "application/zip"})
        assert response.status_code == 201, response.text
        cluster.capture_id = response.json()["id"]
        try:
            yield cluster
        finally:
            client.close()
            stop_all([*cluster.workers, gateway, moto, redis])


def _database() -> Any:
    import contextlib

    if postgres_available():
        return fresh_postgres_db()
    return contextlib.nullcontext(None)


def _fetch_asset(cluster: Cluster, job: dict[str, Any]) -> tuple[bytes, dict[str, Any]]:
    glb = cluster.client.get(job["links"]["mesh_glb"])
    assert glb.status_code == 200 and glb.headers["content-type"] == "model/gltf-binary"
    report = cluster.client.get(job["links"]["report"]).json()
    return glb.content, report


def _follow(cluster: Cluster, job_id: str) -> list[dict[str, Any]]:
    """The job's server-sent events until the stream ends (at the job's end)."""
    events = []
    with cluster.client.stream("GET", f"/api/v1/jobs/{job_id}/events", timeout=180) as stream:
        assert stream.headers["content-type"].startswith("text/event-stream")
        for line in stream.iter_lines():
            if line.startswith("data: "):
                events.append(json.loads(line[6:]))
    return events


def test_a_job_runs_to_a_draco_glb(cluster: Cluster) -> None:
    ready = cluster.client.get("/readyz").json()
    assert ready["status"] == "ok", ready
    job = cluster.submit()
    events = _follow(cluster, job["id"])
    done = events[-1]
    assert done["state"] == "succeeded", done
    progress = [e["progress"] for e in events]
    assert progress == sorted(progress) and len(events) >= 3  # pushed as it went
    assert {e["stage"] for e in events} >= {"mesh", "export"}
    assert done["progress"] == 1.0 and done["stages"][-1] == "export"
    assert set(done["stage_timings"]) == set(done["stages"])
    glb, report = _fetch_asset(cluster, done)
    mesh = check_draco_glb(glb)
    assert report["triangles"] == mesh.face_count and report["vertices"] == mesh.vertex_count
    assert report["stage_stats"]["register"]["points"] > 1000
    ply = cluster.client.get(done["links"]["mesh_ply"])
    assert ply.status_code == 200 and ply.content.startswith(b"ply")

    # The stage outputs went with the export: the same settings again recompute every stage,
    # and give the same mesh.
    again = wait_job(cluster.client, cluster.submit()["id"], {"succeeded", "failed"}, 120)
    assert again["state"] == "succeeded", again
    assert all(again["stage_timings"][s] > 0 for s in again["stages"][:-1]), again
    assert _fetch_asset(cluster, again)[1]["triangles"] == report["triangles"]


def test_a_killed_worker_loses_nothing(cluster: Cluster) -> None:
    job = cluster.submit(meshing={"poisson_depth": 6, "sample_radius_m": 0.016})
    running = cluster.running_stage(job["id"], {"mesh", "remesh"})
    victim = cluster.worker_running(running)
    victim.kill()  # SIGKILL to the worker and its pool processes, mid-stage
    killed_at = time.monotonic()
    assert cluster.client.get(f"/api/v1/jobs/{job['id']}").json()["state"] == "running"
    # Redis would hand the dead worker's message back after its visibility timeout (over an
    # hour); the stage's lease lapses within seconds and the gateway queues it again.
    found = wait_for(lambda: requeued(cluster.gateway.log.read_text(errors="replace"),
                                      job["id"]), 60, "the gateway to queue the stage again")
    print(f"redis: stage {found[0]} queued again {time.monotonic() - killed_at:.1f} s after "
          "the SIGKILL")
    done = wait_job(cluster.client, job["id"], {"succeeded", "failed"},
                    120 - (time.monotonic() - killed_at))
    assert done["state"] == "succeeded", done
    check_draco_glb(_fetch_asset(cluster, done)[0])
    survivor = next(w for w in cluster.workers if w is not victim)
    index, name = found[0]
    assert found == [(index, name)] and done["stages"][index] == name
    assert f"job {job['id']} stage {index} ({name}) starting" in \
        survivor.log.read_text(errors="replace")
    logs = "".join(w.log.read_text(errors="replace") for w in cluster.workers)
    check_stages_ran_once(logs, done, index)
    cluster.workers.remove(victim)
    cluster.add_worker(f"w{len(cluster.workers) + 10}")


def test_redis_restart_mid_job(cluster: Cluster) -> None:
    job = cluster.submit(meshing={"poisson_depth": 6, "sample_radius_m": 0.017})
    cluster.running_stage(job["id"], {"mesh", "remesh"})
    cluster.redis.restart(down_s=1.5)
    done = wait_job(cluster.client, job["id"], {"succeeded", "failed"}, 180)
    assert done["state"] == "succeeded", done
    check_draco_glb(_fetch_asset(cluster, done)[0])
    # The gateway keeps queueing after the restart too.
    later = wait_job(cluster.client, cluster.submit()["id"], {"succeeded", "failed"}, 120)
    assert later["state"] == "succeeded", later


def test_cancel_a_running_job(cluster: Cluster) -> None:
    job = cluster.submit(meshing={"poisson_depth": 6, "sample_radius_m": 0.018})
    running = cluster.running_stage(job["id"], {"mesh", "remesh"})
    response = cluster.client.delete(f"/api/v1/jobs/{job['id']}", headers=cluster.auth)
    assert response.status_code == 200 and response.json()["state"] == "cancelled"
    time.sleep(SETTLE_S)  # long enough for the running stage to end and any next to start
    final = cluster.client.get(f"/api/v1/jobs/{job['id']}").json()
    assert final["state"] == "cancelled" and final["asset_id"] is None
    later = final["stages"][final["stages"].index(running["stage"]) + 1:]
    assert not set(later) & set(final["stage_timings"]), final
    events = cluster.client.get(f"/api/v1/jobs/{job['id']}/events").text
    last = json.loads([ln for ln in events.splitlines() if ln.startswith("data: ")][-1][6:])
    assert last["state"] == "cancelled"
