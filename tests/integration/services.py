"""Real services for the service tests: redis-server, moto's S3 server, PostgreSQL databases,
Celery workers and gateways as separate processes, and small synthetic capture zips."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx

ROOT = Path(__file__).resolve().parents[2]
PG_URL = "postgresql://postgres@127.0.0.1:5432/test"


ANONYMOUS = {"Authorization": ""}
"""Headers of a request with no API key, from a client that sends one by default."""


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def wait_for(predicate: Callable[[], Any], timeout_s: float, what: str,
             interval_s: float = 0.05) -> Any:
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            value = predicate()
        except Exception:  # the service may not answer yet
            value = None
        if value:
            return value
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(interval_s)


def _port_open(port: int) -> bool:
    with socket.socket() as sock:
        sock.settimeout(0.2)
        return sock.connect_ex(("127.0.0.1", port)) == 0


def base_env(**volumesh: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("VOLUMESH_")}
    env["PYTHONPATH"] = str(ROOT)
    env["PYTHONUNBUFFERED"] = "1"
    env.update({f"VOLUMESH_{k.upper()}": v for k, v in volumesh.items()})
    return env


class Process:
    """A child process in its own session, so a kill takes its children too."""

    def __init__(self, cmd: list[str], env: dict[str, str], log: Path) -> None:
        self.cmd, self.env, self.log = cmd, env, log
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> Process:
        self.log.parent.mkdir(parents=True, exist_ok=True)
        out = self.log.open("ab")
        self.proc = subprocess.Popen(self.cmd, env=self.env, cwd=ROOT, stdout=out,
                                     stderr=subprocess.STDOUT, start_new_session=True)
        out.close()
        return self

    @property
    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def kill(self, sig: int = signal.SIGKILL) -> None:
        if self.proc is None:
            return
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.proc.pid, sig)
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.proc.wait(20)

    def stop(self, grace_s: float = 1.0) -> None:
        """SIGTERM to the main process (it stops its children), SIGKILL to all after grace."""
        if self.proc is None:
            return
        if self.alive:
            with contextlib.suppress(ProcessLookupError):
                self.proc.send_signal(signal.SIGTERM)
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.proc.wait(grace_s)
        self.kill(signal.SIGKILL)

    def tail(self, lines: int = 40) -> str:
        if not self.log.is_file():
            return ""
        return "\n".join(self.log.read_text(errors="replace").splitlines()[-lines:])


def stop_all(procs: list[Process], grace_s: float = 1.0) -> None:
    """:meth:`Process.stop` of them all at once: SIGTERM to each, one grace, SIGKILL to all."""
    for proc in procs:
        if proc.alive and proc.proc is not None:
            with contextlib.suppress(ProcessLookupError):
                proc.proc.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + grace_s
    for proc in procs:
        if proc.proc is not None:
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.proc.wait(max(0.0, deadline - time.monotonic()))
    for proc in procs:
        proc.kill(signal.SIGKILL)


class Redis(Process):
    """redis-server on a free port, with an append-only file so a restart keeps the queues."""

    def __init__(self, folder: Path) -> None:
        self.port = free_port()
        folder.mkdir(parents=True, exist_ok=True)
        cmd = ["redis-server", "--port", str(self.port), "--bind", "127.0.0.1",
               "--dir", str(folder), "--appendonly", "yes", "--appendfsync", "always",
               "--save", "", "--protected-mode", "no"]
        super().__init__(cmd, dict(os.environ), folder / "redis.log")

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    def start(self) -> Redis:
        super().start()
        wait_for(lambda: _port_open(self.port), 10, "redis-server")
        return self

    def restart(self, down_s: float = 1.0) -> None:
        self.kill(signal.SIGTERM)  # a clean stop; the AOF has every write (fsync always)
        time.sleep(down_s)
        self.start()


class MotoS3(Process):
    """moto's S3-compatible server, as a separate process."""

    def __init__(self, folder: Path) -> None:
        self.port = free_port()
        moto = shutil.which("moto_server") or "moto_server"
        super().__init__([moto, "-H", "127.0.0.1", "-p", str(self.port)], dict(os.environ),
                         folder / "moto.log")

    @property
    def endpoint(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self) -> MotoS3:
        super().start()
        wait_for(lambda: _port_open(self.port), 30, "moto_server")
        return self

    def make_bucket(self, name: str) -> None:
        import boto3

        boto3.client("s3", endpoint_url=self.endpoint, region_name="us-east-1",
                     aws_access_key_id="test", aws_secret_access_key="test"
                     ).create_bucket(Bucket=name)

    def settings(self, bucket: str) -> dict[str, str]:
        return {"storage_url": f"s3://{bucket}/volumesh", "s3_endpoint_url": self.endpoint,
                "s3_access_key_id": "test", "s3_secret_access_key": "test"}


def postgres_available() -> bool:
    try:
        import psycopg

        with psycopg.connect(PG_URL, connect_timeout=2):
            return True
    except Exception:
        return False


@contextlib.contextmanager
def fresh_postgres_db() -> Iterator[str]:
    """A new, empty database on the local PostgreSQL; dropped afterwards."""
    import psycopg

    name = f"volumesh_test_{uuid.uuid4().hex[:10]}"
    with psycopg.connect(PG_URL, autocommit=True) as conn:
        conn.execute(f'CREATE DATABASE "{name}"')
    try:
        yield PG_URL.rsplit("/", 1)[0] + f"/{name}"
    finally:
        with psycopg.connect(PG_URL, autocommit=True) as conn:
            conn.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')


def worker(env: dict[str, str], log: Path, queues: str = "cpu,gpu,validate",
           name: str | None = None) -> Process:
    cmd = [sys.executable, "-m", "workers", "--queues", queues, "--loglevel", "INFO",
           "--hostname", f"{name or uuid.uuid4().hex[:6]}@test"]
    return Process(cmd, env, log)


def wait_worker_ready(proc: Process, timeout_s: float = 60) -> None:
    wait_for(lambda: " ready." in proc.log.read_text(errors="replace"), timeout_s,
             f"worker ready ({proc.log})")


class Gateway(Process):
    """uvicorn serving ``create_app()`` from the environment, on a free port."""

    def __init__(self, env: dict[str, str], log: Path, workers: int = 1) -> None:
        self.port = free_port()
        cmd = [sys.executable, "-m", "uvicorn", "--factory", "app.main:app_from_env",
               "--host", "127.0.0.1", "--port", str(self.port), "--workers", str(workers),
               "--log-level", "warning", "--timeout-graceful-shutdown", "2"]
        super().__init__(cmd, env, log)

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self) -> Gateway:
        super().start()
        wait_for(lambda: httpx.get(self.url + "/healthz", timeout=1).status_code == 200, 60,
                 f"gateway on {self.port}\n{self.tail()}", interval_s=0.1)
        return self


def create_key(env: dict[str, str], name: str = "test") -> str:
    """An API key made through the real CLI (its last line is the key)."""
    result = subprocess.run([sys.executable, "-m", "app", "keys", "create", "--name", name],
                            env=env, cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    return result.stdout.strip().splitlines()[-1]


@contextlib.contextmanager
def gateway_client(values: dict[str, str]) -> Iterator[tuple[Any, dict[str, str]]]:
    """The gateway in this process (a TestClient) on the settings ``values``, sending a fresh
    API key on every request, and that key's Authorization header."""
    from fastapi.testclient import TestClient

    from app.core.security import create_key
    from app.main import create_app
    from workers.settings import Settings

    app = create_app(Settings.model_validate(values), viewer=False)
    with TestClient(app) as client:
        with app.state.gateway.sessions() as session:
            _, key = create_key(session, "tests")
        client.headers["Authorization"] = f"Bearer {key}"
        yield client, {"Authorization": f"Bearer {key}"}


def upload_capture(client: Any, auth: dict[str, str], zip_path: Path) -> str:
    """POSTs a capture zip; returns its id (fails the test unless the answer is 201)."""
    response = client.post("/api/v1/captures", content=zip_path.read_bytes(),
                           headers={**auth, "Content-Type": "application/zip"})
    assert response.status_code == 201, response.text
    return str(response.json()["id"])


_MADE: dict[str, Path] = {}
"""Zips this test process made, by name (it says their parameters): a later call for the same
one copies it, as the synthesis takes seconds."""


def _copy_made(name: str, zip_path: Path) -> bool:
    """Copies the zip of ``name`` made before to ``zip_path``; whether there was one."""
    made = _MADE.get(name)
    if made is None or not made.is_file():
        return False
    with tempfile.TemporaryDirectory(dir=zip_path.parent) as tmp:
        shutil.copyfile(made, Path(tmp) / zip_path.name)
        (Path(tmp) / zip_path.name).replace(zip_path)
    return True


def make_capture_zip(folder: Path, cameras: int = 4, width: int = 160, height: int = 144,
                     frames: int = 1, seed: int = 0) -> Path:
    """A synthetic capture of the built-in subject, packed as a zip (cached per parameters)."""
    from pipeline.io.capture_io import write_capture, zip_capture
    from pipeline.synth.rig import RigConfig
    from pipeline.synth.scene import SynthConfig, sample_mesh, synthesize

    name = f"capture-{cameras}x{width}x{height}x{frames}-{seed}"
    zip_path = folder / f"{name}.zip"
    if zip_path.is_file() or _copy_made(name, zip_path):
        return zip_path
    config = SynthConfig(camera_count=cameras, frame_count=frames, seed=seed,
                         rig=RigConfig(width=width, height=height))
    meta, views, _ = synthesize(sample_mesh(), config)
    with tempfile.TemporaryDirectory(dir=folder) as tmp:
        write_capture(Path(tmp) / name, meta, views)
        zip_capture(Path(tmp) / name, Path(tmp) / zip_path.name)
        (Path(tmp) / zip_path.name).replace(zip_path)
    _MADE[name] = zip_path
    return zip_path


def make_calibration_zip(folder: Path, cameras: int = 4, width: int = 160, height: int = 144,
                         frames: int = 8, seed: int = 0) -> Path:
    """A ChArUco board moved through the rig of :func:`make_capture_zip` with the same
    parameters (so its calibration fits that capture), packed as a zip; cached."""
    from pipeline.io.capture_io import write_capture, zip_capture
    from pipeline.synth.rig import RigConfig
    from pipeline.synth.scene import SynthConfig, place_subject, sample_mesh, true_cameras
    from pipeline.synth.target import TargetSynthConfig, synthesize_calibration

    name = f"calibration-{cameras}x{width}x{height}x{frames}-{seed}"
    zip_path = folder / f"{name}.zip"
    if zip_path.is_file() or _copy_made(name, zip_path):
        return zip_path
    scene = SynthConfig(camera_count=cameras, seed=seed, rig=RigConfig(width=width, height=height))
    rig = true_cameras(place_subject(sample_mesh(), scene), scene)
    target = TargetSynthConfig(frame_count=frames, seed=seed)
    meta, views, _ = synthesize_calibration(target, cameras=rig)
    with tempfile.TemporaryDirectory(dir=folder) as tmp:
        write_capture(Path(tmp) / name, meta, list(views))
        zip_capture(Path(tmp) / name, Path(tmp) / zip_path.name)
        (Path(tmp) / zip_path.name).replace(zip_path)
    _MADE[name] = zip_path
    return zip_path


def sequence_capture_zip(folder: Path, frames: int = 4, bad_frame: int | None = None,
                         fps: float = 15.0) -> Path:
    """A 4-camera capture of the subject turning, small images; ``bad_frame`` has no depth
    in any camera (all zeros)."""
    from dataclasses import replace

    import numpy as np

    from pipeline.io.capture_io import write_capture, zip_capture
    from pipeline.synth.motion import MotionConfig, synthesize_sequence
    from pipeline.synth.rig import RigConfig
    from pipeline.synth.scene import SynthConfig, sample_mesh

    zip_path = folder / f"sequence-{frames}-{bad_frame}.zip"
    made = f"{zip_path.stem}@{fps:g}"
    if _copy_made(made, zip_path):
        return zip_path
    config = SynthConfig(camera_count=4, frame_count=frames, rig=RigConfig(width=160, height=144))
    meta, views, _ = synthesize_sequence(sample_mesh(), config,
                                         MotionConfig(kind="rigid", frame_rate_hz=fps))
    kept = [replace(v, depth_m=np.zeros_like(v.depth_m)) if v.frame_index == bad_frame else v
            for v in views]
    with tempfile.TemporaryDirectory(dir=folder) as tmp:
        write_capture(Path(tmp) / "capture", meta, kept)
        zip_capture(Path(tmp) / "capture", zip_path)
    _MADE[made] = zip_path
    return zip_path


def wait_job(client: httpx.Client, job_id: str, states: set[str], timeout_s: float,
             headers: dict[str, str] | None = None) -> dict[str, Any]:
    def check() -> dict[str, Any] | None:
        job = client.get(f"/api/v1/jobs/{job_id}", headers=headers).json()
        return job if job["state"] in states else None

    last: dict[str, Any] = {}
    try:
        return wait_for(check, timeout_s, f"job {job_id} to reach {states}", interval_s=0.2)
    except TimeoutError:
        last = client.get(f"/api/v1/jobs/{job_id}", headers=headers).json()
        raise TimeoutError(f"job {job_id} did not reach {states}: {last}") from None


def check_draco_glb(data: bytes) -> Any:
    """Assert ``data`` is a GLB whose mesh is Draco-compressed and decodes; returns the mesh."""
    import json
    import struct

    from pipeline.io.gltf_read import decode_glb

    magic, version, _ = struct.unpack_from("<III", data, 0)
    assert (magic, version) == (0x46546C67, 2), "not a glTF 2.0 binary"
    json_length = struct.unpack_from("<I", data, 12)[0]
    doc = json.loads(data[20:20 + json_length])
    assert "KHR_draco_mesh_compression" in doc.get("extensionsRequired", [])
    primitive = doc["meshes"][0]["primitives"][0]
    assert "KHR_draco_mesh_compression" in primitive.get("extensions", {})
    mesh = decode_glb(data)
    assert mesh.face_count > 100 and mesh.vertex_count > 100
    return mesh


FAST_JOB = {"enhance": False, "target_edge_length_m": 0.04,
            "meshing": {"poisson_depth": 6, "sample_radius_m": 0.015},
            "remesh": {"iterations": 1}}
"""Job options that keep a test reconstruction to a few seconds on two cores."""
