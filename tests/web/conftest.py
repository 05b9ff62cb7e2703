"""Fixtures of the browser tests: Playwright, a live gateway with a worker, stored assets."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from pipeline.io.gltf_io import encode_glb
from tests.web.harness import (
    Browsers,
    LiveGateway,
    bumpy_torus,
    live_gateway,
    require_chromium,
    synthetic_capture_zip,
)

ARTIFACTS = Path(__file__).resolve().parents[2] / "test-artifacts" / "web"


@pytest.fixture(scope="session")
def artifacts() -> Path:
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    return ARTIFACTS


@pytest.fixture(scope="session")
def playwright() -> Iterator[Any]:
    try:
        require_chromium()
    except RuntimeError as exc:
        pytest.fail(str(exc), pytrace=False)
    from playwright.sync_api import sync_playwright

    with sync_playwright() as driver:
        yield driver


@pytest.fixture(scope="session")
def browsers(playwright: Any) -> Iterator[Browsers]:
    """One Chromium per backend for the session; each page gets a fresh context of it."""
    pool = Browsers(playwright)
    try:
        yield pool
    finally:
        pool.close()


@pytest.fixture(scope="session")
def gateway(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveGateway]:
    with live_gateway(tmp_path_factory.mktemp("volumesh-web")) as live:
        yield live


@pytest.fixture(scope="session")
def capture_zip(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return synthetic_capture_zip(tmp_path_factory.mktemp("capture"))


@pytest.fixture(scope="session")
def job(gateway: LiveGateway, capture_zip: Path) -> dict[str, Any]:
    """A real job: the capture uploaded, reconstructed and exported by the worker."""
    finished = gateway.run_job(capture_zip, enhance=False)
    assert finished["state"] == "succeeded", finished
    return finished


@pytest.fixture(scope="session")
def torus_asset(gateway: LiveGateway) -> str:
    """A 100k-triangle Draco asset made by the project's export, with a report and a rig."""
    mesh = bumpy_torus()
    report = {"mesh": {"vertices": mesh.vertex_count, "triangles": mesh.face_count},
              "stage_timings_s": {"mesh": 1.5, "export": 0.1},
              "rig": {"world_from_depth": ring_rig()}}
    return gateway.store_asset(encode_glb(mesh), report)


@pytest.fixture(scope="session")
def raw_torus_asset(gateway: LiveGateway) -> str:
    """The same torus with 4 mm of noise: the 'raw' side of a before/after comparison."""
    return gateway.store_asset(encode_glb(bumpy_torus(noise_m=0.004)))


def ring_rig(count: int = 8) -> dict[str, list[list[float]]]:
    """world_from_depth of `count` cameras on two rings looking at (0, 0.9, 0) (OpenCV axes)."""
    rig = {}
    for k in range(count):
        angle = 2 * np.pi * k / count
        eye = np.array([2 * np.cos(angle), 2.0 if k % 2 else 1.0, 2 * np.sin(angle)])
        forward = np.array([0, 0.9, 0]) - eye
        forward /= np.linalg.norm(forward)
        right = np.cross([0.0, -1.0, 0.0], forward)
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        pose = np.eye(4)
        pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, down, forward, eye
        rig[f"cam{k}"] = pose.tolist()
    return rig
