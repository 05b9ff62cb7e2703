"""What the browser tests and benchmarks/viewer.py share: a real gateway with a worker, assets
in its store, meshes, Debian's Chromium driven by Playwright, and screenshot pixel checks."""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from pipeline.geometry.mesh import TriangleMesh

CHROMIUM = Path("/usr/bin/chromium")
# docs/decisions/headless-webgpu.md: WebGPU runs on SwiftShader's Vulkan with exactly these four;
# with none of them WebGPURenderer finds no adapter and falls back to WebGL2.
WEBGPU_FLAGS = ["--enable-unsafe-webgpu", "--enable-features=Vulkan", "--use-vulkan=swiftshader",
                "--use-angle=swiftshader"]
BASE_FLAGS = ["--no-sandbox", "--disable-background-networking", "--disable-component-update",
              "--disable-sync", "--no-first-run"]
BACKGROUND_RGB = np.array([0x1D, 0x20, 0x26])  # static/app/render.js BACKGROUND
VIEWPORT = {"width": 960, "height": 640}


def require_chromium() -> Path:
    if not CHROMIUM.is_file():
        raise RuntimeError(f"{CHROMIUM} is missing: the browser tests drive Debian's Chromium; "
                           "install it with `make setup` (apt-get install -y chromium)")
    return CHROMIUM


# --- meshes ----------------------------------------------------------------------------------


def bumpy_torus(nu: int = 250, nv: int = 200, noise_m: float = 0.0, seed: int = 0
                ) -> TriangleMesh:
    """A coloured torus standing about 1 m up, 2*nu*nv triangles (100k by default), metres."""
    u = np.linspace(0, 2 * np.pi, nu, endpoint=False)
    v = np.linspace(0, 2 * np.pi, nv, endpoint=False)
    uu, vv = np.meshgrid(u, v, indexing="ij")
    tube = 0.25 * (1 + 0.08 * np.sin(7 * uu) * np.cos(5 * vv))
    ring = 0.6 + tube * np.cos(vv)
    vertices = np.stack([ring * np.cos(uu), tube * np.sin(vv) + 0.9, ring * np.sin(uu)], -1)
    vertices = vertices.reshape(-1, 3)
    if noise_m:
        vertices = vertices + np.random.default_rng(seed).normal(0, noise_m, vertices.shape)
    i, j = np.arange(nu)[:, None], np.arange(nv)[None, :]
    a, b = i * nv + j, ((i + 1) % nu) * nv + j
    c, d = ((i + 1) % nu) * nv + (j + 1) % nv, i * nv + (j + 1) % nv
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                            np.stack([a, c, d], -1).reshape(-1, 3)]).astype(np.int32)
    rgb = np.stack([0.5 + 0.5 * np.cos(uu), 0.5 + 0.5 * np.sin(vv), 0.6 + 0 * uu], -1)
    return TriangleMesh(vertices, faces, (rgb.reshape(-1, 3) * 255).astype(np.uint8))


def with_error_attribute(glb: bytes, error_m: NDArray[np.float32]) -> bytes:
    """A plain (non-Draco) GLB with a per-vertex ``_ERROR_M`` float attribute added."""
    if struct.unpack_from("<I", glb, 0)[0] != 0x46546C67:
        raise ValueError("not a GLB")
    json_len = struct.unpack_from("<I", glb, 12)[0]
    doc = json.loads(glb[20:20 + json_len])
    bin_len = struct.unpack_from("<I", glb, 20 + json_len)[0]
    binary = bytearray(glb[28 + json_len: 28 + json_len + bin_len])
    primitive = doc["meshes"][0]["primitives"][0]
    count = doc["accessors"][primitive["attributes"]["POSITION"]]["count"]
    if "extensions" in primitive or len(error_m) != count:
        raise ValueError("with_error_attribute needs a plain GLB and one error per vertex")
    doc["bufferViews"].append({"buffer": 0, "byteOffset": len(binary),
                               "byteLength": 4 * count, "target": 34962})
    binary += np.asarray(error_m, np.float32).tobytes()
    doc["accessors"].append({"bufferView": len(doc["bufferViews"]) - 1, "componentType": 5126,
                             "count": count, "type": "SCALAR"})
    primitive["attributes"]["_ERROR_M"] = len(doc["accessors"]) - 1
    doc["buffers"][0]["byteLength"] = len(binary)
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    total = 12 + 8 + len(text) + 8 + len(binary)
    return b"".join([struct.pack("<III", 0x46546C67, 2, total),
                     struct.pack("<II", len(text), 0x4E4F534A), text,
                     struct.pack("<II", len(binary), 0x004E4942), bytes(binary)])


# --- the gateway -----------------------------------------------------------------------------


ROOT = Path(__file__).resolve().parents[2]


class Child:
    """A child process in its own session (a stop takes its children too), output to a log."""

    def __init__(self, cmd: list[str], env: dict[str, str], log: Path) -> None:
        log.parent.mkdir(parents=True, exist_ok=True)
        self.log = log
        with log.open("ab") as out:
            self.proc = subprocess.Popen(cmd, env=env, cwd=ROOT, stdout=out,
                                         stderr=subprocess.STDOUT, start_new_session=True)

    def wait_for(self, predicate: Any, timeout_s: float, what: str) -> None:
        deadline = time.monotonic() + timeout_s
        while True:
            with contextlib.suppress(Exception):
                if predicate():
                    return
            if self.proc.poll() is not None or time.monotonic() > deadline:
                tail = self.log.read_text(errors="replace")[-3000:]
                raise RuntimeError(f"{what} did not come up (exit {self.proc.poll()}):\n{tail}")
            time.sleep(0.1)

    def stop(self) -> None:
        stop_children([self])


def stop_children(children: list[Child], grace_s: float = 10.0) -> None:
    """SIGTERM to every child's group at once, one grace for all, then SIGKILL to those
    left."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        running = [c for c in children if c.proc.poll() is None]
        for child in running:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(child.proc.pid, sig)
        deadline = time.monotonic() + grace_s
        for child in running:
            with contextlib.suppress(subprocess.TimeoutExpired):
                child.proc.wait(max(0.0, deadline - time.monotonic()))


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@dataclass
class LiveGateway:
    """uvicorn serving create_app() and a Celery worker on the embedded broker, in data_dir."""

    data_dir: Path
    url: str
    key: str
    owner: str
    """What the key's work is owned by (assets stored here are its owner's)."""

    @property
    def auth(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.key}"}

    def store_asset(self, glb: bytes, report: dict[str, Any] | None = None) -> str:
        """Puts an asset in the gateway's store as a finished job would; returns its id."""
        from workers.context import WorkerContext
        from workers.models import Capture, Job, new_id
        from workers.settings import Settings

        ctx = WorkerContext.create(Settings(data_dir=self.data_dir))
        capture_id, job_id = new_id(), new_id()
        with ctx.store.sessions.begin() as session:
            session.add(Capture(id=capture_id, sha256=hashlib.sha256(job_id.encode()).hexdigest(),
                                size_bytes=0, storage_key=f"captures/{capture_id}.zip",
                                state="ready", cameras=8, frames=1))
            session.add(Job(id=job_id, capture_id=capture_id, state="running",
                            stages=["export"], stage="export", owner=self.owner))
        files = {"mesh.glb": _put(ctx, job_id, "mesh.glb", glb, "model/gltf-binary")}
        if report is not None:
            files["report.json"] = _put(ctx, job_id, "report.json", json.dumps(report).encode(),
                                        "application/json")
        if not ctx.store.succeed(job_id, job_id, files, 0.0):
            raise RuntimeError("the job store refused the asset")
        return job_id


    def run_job(self, capture_zip: Path, timeout_s: float = 120, **options: Any
                ) -> dict[str, Any]:
        """Uploads a capture, runs a job on it through the API and returns the finished job."""
        import httpx

        with httpx.Client(base_url=self.url, headers=self.auth, timeout=60) as client:
            upload = client.post("/api/v1/captures", content=capture_zip.read_bytes(),
                                 headers={"Content-Type": "application/zip"})
            upload.raise_for_status()
            job = client.post("/api/v1/jobs", json={"capture_id": upload.json()["id"],
                                                    **options})
            job.raise_for_status()
            deadline = time.monotonic() + timeout_s
            while time.monotonic() < deadline:
                state = client.get(f"/api/v1/jobs/{job.json()['id']}").json()
                if state["state"] in ("succeeded", "failed", "cancelled"):
                    return dict(state)
                time.sleep(0.25)
        raise TimeoutError(f"job {job.json()['id']} unfinished after {timeout_s} s: {state}")


def synthetic_capture_zip(folder: Path, width: int = 160, height: int = 144, seed: int = 0
                          ) -> Path:
    """An 8-camera capture of the built-in subject (small images: a job takes seconds)."""
    from pipeline.io.capture_io import write_capture, zip_capture
    from pipeline.synth.rig import RigConfig
    from pipeline.synth.scene import SynthConfig, sample_mesh, synthesize

    config = SynthConfig(seed=seed, rig=RigConfig(width=width, height=height))
    meta, views, _ = synthesize(sample_mesh(), config)
    write_capture(folder / "capture", meta, views)
    zip_capture(folder / "capture", folder / "capture.zip")
    return folder / "capture.zip"


def _put(ctx: Any, asset_id: str, name: str, data: bytes, content_type: str) -> dict[str, Any]:
    key = f"assets/{asset_id}/{name}"
    ctx.storage.put_bytes(key, data)
    return {"key": key, "sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data),
            "content_type": content_type}


@contextlib.contextmanager
def live_gateway(data_dir: Path) -> Iterator[LiveGateway]:
    """The gateway (uvicorn, create_app from VOLUMESH_* settings) and one worker for every
    queue, on the embedded broker and store in data_dir, with an API key."""
    import httpx

    from app.core.security import create_key, owner_of
    from workers.db import init_db, make_engine, make_sessionmaker
    from workers.settings import Settings

    env = {k: v for k, v in os.environ.items() if not k.startswith("VOLUMESH_")}
    env.update(PYTHONPATH=str(ROOT), PYTHONUNBUFFERED="1", VOLUMESH_DATA_DIR=str(data_dir))
    engine = make_engine(Settings(data_dir=data_dir))
    init_db(engine)
    with make_sessionmaker(engine)() as session:
        row, key = create_key(session, "web-tests")
    engine.dispose()
    port = free_port()
    work = Child([sys.executable, "-m", "workers", "--queues", "cpu,gpu,validate",
                  "--concurrency", "1", "--hostname", f"web-{port}@localhost"],
                 env, data_dir / "worker.log")
    gateway = Child([sys.executable, "-m", "uvicorn", "--factory", "app.main:app_from_env",
                     "--host", "127.0.0.1", "--port", str(port), "--log-level", "warning"],
                    env, data_dir / "gateway.log")
    url = f"http://127.0.0.1:{port}"
    try:
        gateway.wait_for(lambda: httpx.get(url + "/healthz", timeout=1).status_code == 200,
                         60, "the gateway")
        work.wait_for(lambda: " ready." in work.log.read_text(errors="replace"), 60,
                      "the worker")
        yield LiveGateway(data_dir, url, key, owner_of(row.id, None))
    finally:
        # An idle Celery worker takes about 5 s to leave on SIGTERM; nothing waits for it.
        stop_children([gateway, work], grace_s=1.0)


# --- the browser -----------------------------------------------------------------------------


@dataclass
class ConsoleLog:
    messages: list[tuple[str, str, str]] = field(default_factory=list)

    def errors(self, allowed_urls: tuple[str, ...] = ()) -> list[str]:
        """Console errors and uncaught exceptions, less failed loads of the allowed URLs."""
        return [f"{kind}: {text} ({url})" for kind, text, url in self.messages
                if kind in ("error", "pageerror")
                and not any(url.startswith(a) for a in allowed_urls if url)]


class Browsers:
    """One headless Chromium per backend, each started at its first page and kept: a page of
    :func:`viewer_page` then costs a fresh context (an empty profile of its own, no cookies or
    storage shared) rather than a whole browser start."""

    def __init__(self, playwright: Any) -> None:
        self.playwright = playwright
        self.running: dict[str, Any] = {}

    def browser(self, backend: str) -> Any:
        if backend not in self.running:
            self.running[backend] = self.playwright.chromium.launch(
                executable_path=str(require_chromium()), headless=True,
                args=_flags(backend))
        return self.running[backend]

    def close(self) -> None:
        for browser in self.running.values():
            with contextlib.suppress(Exception):
                browser.close()
        self.running.clear()


def _flags(backend: str) -> list[str]:
    if backend not in ("webgpu", "webgl2"):
        raise ValueError(f"backend must be webgpu or webgl2, got {backend!r}")
    return BASE_FLAGS + (WEBGPU_FLAGS if backend == "webgpu" else [])


@contextlib.contextmanager
def viewer_page(playwright: Any, backend: str, api_key: str | None = None
                ) -> Iterator[tuple[Any, ConsoleLog]]:
    """A page in a fresh Chromium profile; `backend` 'webgpu' adds the GPU flags, 'webgl2' none.
    With `api_key` the viewer holds that key (as if saved under "API key") from the start.

    `playwright` is Playwright's driver (a browser started for the page alone) or a
    :class:`Browsers` (a new context of its browser for the backend)."""
    args = _flags(backend)
    with contextlib.ExitStack() as stack:
        if isinstance(playwright, Browsers):
            context = playwright.browser(backend).new_context(viewport=VIEWPORT)
        else:
            profile = stack.enter_context(
                tempfile.TemporaryDirectory(prefix="volumesh-chromium-"))
            context = playwright.chromium.launch_persistent_context(
                profile, executable_path=str(require_chromium()), headless=True, args=args,
                viewport=VIEWPORT)
        try:
            if api_key is not None:
                context.add_init_script(f"localStorage.setItem('volumesh.apiKey', "
                                        f"{json.dumps(api_key)})")
            page = context.pages[0] if context.pages else context.new_page()
            log = ConsoleLog()
            page.on("console", lambda m: log.messages.append(
                (m.type, m.text, (m.location or {}).get("url", ""))))
            page.on("pageerror", lambda e: log.messages.append(("pageerror", str(e), "")))
            yield page, log
        finally:
            context.close()


def wait_state(page: Any, timeout_ms: float = 30_000) -> str:
    """Waits until the page leaves 'loading'; returns the state (ready or error)."""
    page.wait_for_function("document.body.dataset.state !== 'loading'", timeout=timeout_ms)
    return str(page.evaluate("document.body.dataset.state"))


def viewport_pixels(page: Any, save_to: Path | None = None) -> NDArray[np.int16]:
    """(H, W, 3) screenshot of the 3D view (the side panel left out)."""
    from PIL import Image

    png = page.locator("#viewport").screenshot()
    if save_to is not None:
        save_to.parent.mkdir(parents=True, exist_ok=True)
        save_to.write_bytes(png)
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(np.int16)


def foreground(pixels: NDArray[np.int16], tolerance: int = 12) -> NDArray[np.bool_]:
    """Pixels that differ from the viewer's background by more than `tolerance` levels."""
    return np.abs(pixels - BACKGROUND_RGB).max(axis=-1) > tolerance
