"""`volumesh serve` with no settings: gateway plus embedded workers, no outside services."""

from __future__ import annotations

import signal
import sys
from pathlib import Path

import httpx
import pytest

from tests.integration.services import (
    ANONYMOUS,
    FAST_JOB,
    Process,
    base_env,
    check_draco_glb,
    free_port,
    make_capture_zip,
    wait_for,
    wait_job,
)

pytestmark = pytest.mark.slow


def test_serve_runs_a_job_end_to_end(tmp_path: Path) -> None:
    data_dir = tmp_path / "data"
    port = free_port()
    env = base_env()  # no VOLUMESH_* at all: the embedded default
    serve = Process([sys.executable, "-m", "app", "serve", "--port", str(port),
                     "--data-dir", str(data_dir)], env, tmp_path / "serve.log").start()
    client = httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=60)
    try:
        wait_for(lambda: client.get("/readyz").status_code == 200, 60,
                 f"serve to be ready\n{serve.tail()}", interval_s=0.2)
        key_file = data_dir / "api-key.txt"
        key = key_file.read_text().strip()
        assert oct(key_file.stat().st_mode & 0o777) == "0o600"
        assert key in serve.log.read_text()  # shown once, on first start
        auth = {"Authorization": f"Bearer {key}"}
        client.headers.update(auth)
        capture = make_capture_zip(tmp_path, cameras=4, width=160, height=144)
        upload = client.post("/api/v1/captures", headers=auth, files={
            "file": ("capture.zip", capture.read_bytes(), "application/zip")})
        assert upload.status_code == 201, upload.text
        job = client.post("/api/v1/jobs", headers=auth,
                          json={"capture_id": upload.json()["id"], **FAST_JOB})
        assert job.status_code == 202, job.text
        done = wait_job(client, job.json()["id"], {"succeeded", "failed"}, 180)
        assert done["state"] == "succeeded", (done, serve.tail())
        glb = client.get(done["links"]["mesh_glb"])
        check_draco_glb(glb.content)
        assert client.get("/metrics").status_code == 200  # the first key is an admin key
        assert client.get(done["links"]["self"], headers=ANONYMOUS).status_code == 401
        # Everything lives in the data folder: job store, broker files, storage.
        assert (data_dir / "volumesh.db").is_file() and (data_dir / "broker").is_dir()
        assert list((data_dir / "storage" / "assets").rglob("mesh.glb"))
        assert serve.proc is not None
        workers = _children(serve.proc.pid)
        assert sorted("--queues" in c for c in workers.values()) == [True, True], workers
    finally:
        client.close()
        serve.stop(grace_s=15.0)
    assert not serve.alive
    # The embedded workers went with it (no orphans holding the broker folder).
    assert _gone(workers)


def _children(pid: int) -> dict[int, str]:
    """Direct children of ``pid``: pid -> command line."""
    found = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            parent = int(stat.read_text().rsplit(")", 1)[1].split()[1])
            if parent == pid:
                cmdline = (stat.parent / "cmdline").read_bytes().replace(b"\0", b" ")
                found[int(stat.parent.name)] = cmdline.decode(errors="replace")
        except (OSError, IndexError, ValueError):
            continue
    return found


def _gone(processes: dict[int, str]) -> bool:
    for pid, cmdline in processes.items():
        try:
            now = (Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ")
                   .decode(errors="replace"))
        except OSError:
            continue
        if now == cmdline:
            return False
    return True


def test_serve_stops_its_workers_on_sigterm(tmp_path: Path) -> None:
    port = free_port()
    serve = Process([sys.executable, "-m", "app", "serve", "--port", str(port),
                     "--data-dir", str(tmp_path / "data")], base_env(),
                    tmp_path / "serve.log").start()
    assert serve.proc is not None
    try:
        wait_for(lambda: httpx.get(f"http://127.0.0.1:{port}/healthz").status_code == 200, 60,
                 "serve to start", interval_s=0.2)
        workers = wait_for(lambda: _children(serve.proc.pid) if serve.proc else None, 10,
                           "embedded workers")
        serve.proc.send_signal(signal.SIGTERM)
        serve.proc.wait(30)
        assert serve.proc.returncode == 0, serve.tail()
        wait_for(lambda: _gone(workers), 5, "embedded workers to exit")
    finally:
        serve.stop()


def test_jobs_survive_a_killed_serve_and_the_sample_is_ready(tmp_path: Path) -> None:
    data_dir = tmp_path / "data"
    port = free_port()
    cmd = [sys.executable, "-m", "app", "serve", "--port", str(port), "--data-dir",
           str(data_dir)]
    first = Process(cmd, base_env(), tmp_path / "serve-1.log").start()
    client = httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=60)
    try:
        wait_for(lambda: client.get("/readyz").status_code == 200, 60, "serve", interval_s=0.2)
        auth = {"Authorization": f"Bearer {(data_dir / 'api-key.txt').read_text().strip()}"}
        client.headers.update(auth)
        capture = make_capture_zip(tmp_path, cameras=4, width=160, height=144)
        upload = client.post("/api/v1/captures", content=capture.read_bytes(),
                             headers={**auth, "Content-Type": "application/zip"})
        assert upload.status_code == 201, upload.text
        job = client.post("/api/v1/jobs", headers=auth, json={
            "capture_id": upload.json()["id"], **FAST_JOB,
            "meshing": {"poisson_depth": 6, "sample_radius_m": 0.014}}).json()
        wait_for(lambda: client.get(f"/api/v1/jobs/{job['id']}").json()["stage"]
                 in ("mesh", "remesh"), 120, "the job to be mid-way", interval_s=0.05)
        first.kill()  # SIGKILL: no clean shutdown of the gateway or its workers
        second = Process([*cmd, "--sample"], base_env(), tmp_path / "serve-2.log").start()
        try:
            wait_for(lambda: client.get("/readyz").status_code == 200, 120,
                     f"serve to restart\n{second.tail()}", interval_s=0.2)
            done = wait_job(client, job["id"], {"succeeded", "failed"}, 180)
            assert done["state"] == "succeeded", (done, second.tail())
            check_draco_glb(client.get(done["links"]["mesh_glb"]).content)
            captures = client.get("/api/v1/captures").json()["items"]
            assert any(c["cameras"] == 8 and c["state"] == "ready" for c in captures), captures
        finally:
            # Nothing more to see: SIGKILL, its workers get their SIGTERM from the kernel
            # (PR_SET_PDEATHSIG); test_serve_runs_a_job_end_to_end checks a graceful stop.
            second.kill()
    finally:
        client.close()
        first.stop()
