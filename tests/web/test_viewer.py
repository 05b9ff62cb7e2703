"""The viewer in Debian's Chromium against a live gateway: WebGPU and WebGL2 renders judged by
their pixels, quality views, sequences, and errors shown as the API's own message."""

from __future__ import annotations

import json
import urllib.parse
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from numpy.typing import NDArray

from pipeline.io.gltf_io import encode_glb
from tests.web.harness import (
    Browsers,
    LiveGateway,
    bumpy_torus,
    foreground,
    synthetic_capture_zip,
    viewer_page,
    viewport_pixels,
    wait_state,
    with_error_attribute,
)

pytestmark = pytest.mark.timeout(120)


@dataclass
class Render:
    state: str
    message: str
    stats: dict[str, Any]
    pixels: NDArray[np.int16]
    errors: list[str]


@pytest.fixture(scope="module")
def renders(browsers: Browsers, gateway: LiveGateway, job: dict[str, Any], artifacts: Path
            ) -> dict[str, Render]:
    """A real job's asset, rendered once per backend in a fresh browser."""
    found = {}
    for backend in ("webgpu", "webgl2"):
        with viewer_page(browsers, backend, gateway.key) as (page, log):
            page.goto(f"{gateway.url}/?asset={job['asset_id']}")
            state = wait_state(page)
            found[backend] = Render(
                state=state, message=page.inner_text("#message"),
                stats=page.evaluate("window.viewerStats"),
                pixels=viewport_pixels(page, artifacts / f"asset-{backend}.png"),
                errors=log.errors())
    return found


@pytest.mark.parametrize("backend", ["webgpu", "webgl2"])
def test_job_asset_renders(renders: dict[str, Render], backend: str, gateway: LiveGateway,
                           job: dict[str, Any]) -> None:
    render = renders[backend]
    assert render.state == "ready", render.message
    report = httpx.get(f"{gateway.url}{job['links']['report']}", headers=gateway.auth).json()
    assert render.stats["backend"] == backend
    assert render.stats["triangles"] == report["triangles"]
    assert render.stats["bytes"] == report["glb_bytes"]
    assert render.stats["decodeMs"] > 0
    mask = foreground(render.pixels)
    assert 0.03 < mask.mean() < 0.6, f"{mask.mean():.1%} of the view differs from the background"
    # Shaded and coloured, not a flat silhouette.
    assert render.pixels[mask].std(axis=0).min() > 10
    assert render.errors == []


def test_backends_agree(renders: dict[str, Render]) -> None:
    gpu, gl = renders["webgpu"], renders["webgl2"]
    mask_gpu, mask_gl = foreground(gpu.pixels), foreground(gl.pixels)
    union = mask_gpu | mask_gl
    assert (mask_gpu & mask_gl).sum() / union.sum() > 0.95
    assert np.abs(gpu.pixels - gl.pixels)[union].mean() < 12


def _settle(page: Any) -> None:
    page.evaluate("new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))")
    page.wait_for_timeout(150)


def _near(pixels: NDArray[np.int16], rgb: tuple[int, ...], tolerance: int) -> float:
    return float((np.abs(pixels - np.array(rgb)).max(axis=-1) <= tolerance).mean())


def test_quality_views(browsers: Browsers, gateway: LiveGateway, torus_asset: str,
                       raw_torus_asset: str, artifacts: Path) -> None:
    with viewer_page(browsers, "webgpu", gateway.key) as (page, log):
        page.goto(f"{gateway.url}/?asset={torus_asset}&compare={raw_torus_asset}")
        assert wait_state(page) == "ready", page.inner_text("#message")
        page.wait_for_function("!document.getElementById('compare-mode').disabled")
        shots = {}

        def shoot(name: str) -> NDArray[np.int16]:
            _settle(page)
            shots[name] = viewport_pixels(page, artifacts / f"quality-{name}.png")
            return shots[name]

        enhanced = shoot("enhanced")
        page.select_option("#compare-mode", "raw")
        raw = shoot("raw")
        page.select_option("#compare-mode", "split")
        split = shoot("split")
        height, width = split.shape[:2]
        rows = slice(0, height - 60)  # the split slider sits at the bottom
        left, right = slice(0, width // 2 - 8), slice(width // 2 + 8, width)
        assert np.abs(split[rows, left] - raw[rows, left]).mean() < 2
        assert np.abs(split[rows, right] - enhanced[rows, right]).mean() < 2
        assert np.abs(raw - enhanced)[foreground(enhanced)].mean() > 3  # the two differ

        page.select_option("#compare-mode", "enhanced")
        page.select_option("#shading", "bands")
        bands = shoot("bands")
        solid = foreground(bands).mean()
        # Green 0-30°, yellow 31-60°, red 61-90° (darkened up to 45 % at grazing angles).
        for hue in ((47, 168, 102), (232, 197, 71), (217, 83, 79)):
            found = max(_near(bands, tuple(int(c * f) for c in hue), 18) for f in (1, .85, .7))
            assert found > 0.01 * solid, f"band colour {hue} missing"
        assert page.locator("#legend .swatch").count() == 3

        page.select_option("#shading", "normals")
        normals = shoot("normals")
        assert np.abs(normals - bands)[foreground(bands)].mean() > 20

        page.select_option("#shading", "colour")
        page.check("#wireframe")
        wire = shoot("wireframe")
        assert np.abs(wire - enhanced)[foreground(enhanced)].mean() > 5
        page.uncheck("#wireframe")

        page.check("#frusta")
        frusta = shoot("frusta")
        assert _near(frusta, (127, 180, 255), 30) > _near(enhanced, (127, 180, 255), 30) + 1e-4
        assert log.errors() == []


def test_error_heat_map(browsers: Browsers, gateway: LiveGateway, artifacts: Path) -> None:
    mesh = bumpy_torus(nu=120, nv=80)
    x = mesh.vertices_m[:, 0]
    error_m = (0.004 * (x - x.min()) / np.ptp(x)).astype(np.float32)  # 0 -> 4 mm, left -> right
    glb = with_error_attribute(encode_glb(mesh, draco=None), error_m)
    asset = gateway.store_asset(glb, {"ground_truth": {"rms_m": 0.0021, "p95_m": 0.0038}})
    with viewer_page(browsers, "webgpu", gateway.key) as (page, log):
        page.goto(f"{gateway.url}/?asset={asset}")
        assert wait_state(page) == "ready", page.inner_text("#message")
        page.select_option("#shading", "error")
        _settle(page)
        heat = viewport_pixels(page, artifacts / "quality-error.png")
        mask = foreground(heat)
        columns = np.nonzero(mask.any(axis=0))[0]
        third = (columns[-1] - columns[0]) // 3
        left = heat[:, columns[0]: columns[0] + third][mask[:, columns[0]: columns[0] + third]]
        right = heat[:, columns[-1] - third: columns[-1]][mask[:, columns[-1] - third: columns[-1]]]
        assert left[:, 2].mean() > left[:, 0].mean() + 30  # blue end: small error on the left
        assert right[:, 0].mean() > right[:, 2].mean() + 30  # red end: large error on the right
        assert "mm" in page.inner_text("#legend")
        assert "ground_truth.p95_m" in page.inner_text("#report")
        assert log.errors() == []


def test_sequence_plays_and_scrubs(browsers: Browsers, gateway: LiveGateway, torus_asset: str,
                                   raw_torus_asset: str, artifacts: Path) -> None:
    frames = [torus_asset, raw_torus_asset, torus_asset]
    manifest = {"version": 1, "fps": 12, "bounds": {"min": [-0.9, 0.6, -0.9],
                                                    "max": [0.9, 1.2, 0.9]},
                "frames": [{"url": f"{gateway.url}/api/v1/assets/{a}/mesh.glb"} for a in frames]}
    # The gateway validates manifests with the schema it documents.
    from app.web import SequenceManifest

    SequenceManifest.model_validate(manifest)
    data_url = "data:application/json," + urllib.parse.quote(json.dumps(manifest))
    with viewer_page(browsers, "webgpu", gateway.key) as (page, log):
        page.goto(f"{gateway.url}/?sequence={urllib.parse.quote(data_url, safe='')}")
        assert wait_state(page) == "ready", page.inner_text("#message")
        assert page.is_visible("#sequence-bar")
        assert page.inner_text("#frame-label") == "1 / 3"
        page.click("#play")
        page.wait_for_function("window.viewerStats.sequence.shown >= 5", timeout=20_000)
        page.click("#play")  # pause
        page.fill("#scrub", "1")
        page.dispatch_event("#scrub", "input")
        page.wait_for_function("window.viewerStats.sequence.current === 1")
        _settle(page)
        pixels = viewport_pixels(page, artifacts / "sequence-frame2.png")
        assert 0.02 < foreground(pixels).mean() < 0.6
        assert page.inner_text("#frame-label") == "2 / 3"
        assert log.errors() == []


def test_broken_zip_shows_the_api_message(browsers: Browsers, gateway: LiveGateway,
                                          artifacts: Path) -> None:
    broken = b"PK\x03\x04" + b"\x00" * 60 + b"this is no capture"
    with viewer_page(browsers, "webgl2") as (page, log):
        page.goto(gateway.url + "/")
        assert wait_state(page) == "ready", page.inner_text("#message")
        page.fill("#api-key", gateway.key)
        page.click("#api-key-form button")
        # Dropped on the page (the upload test uses the file chooser).
        dropped = page.evaluate_handle(
            """(bytes) => {
                const transfer = new DataTransfer();
                transfer.items.add(new File([new Uint8Array(bytes)], 'broken.zip',
                                            {type: 'application/zip'}));
                return transfer;
            }""", list(broken))
        page.dispatch_event("#viewport", "dragover", {"dataTransfer": dropped})
        assert "drop-over" in (page.get_attribute("body", "class") or "")
        page.dispatch_event("#viewport", "drop", {"dataTransfer": dropped})
        page.wait_for_function("document.body.dataset.upload === 'error'", timeout=60_000)
        shown = page.inner_text("#message")
        page.screenshot(path=str(artifacts / "broken-zip.png"))
        problem = httpx.post(f"{gateway.url}/api/v1/captures", content=broken, timeout=60,
                             headers={"Authorization": f"Bearer {gateway.key}",
                                      "Content-Type": "application/zip"})
        assert 400 <= problem.status_code < 500
        assert shown.strip() == problem.json()["detail"]
        assert log.errors(allowed_urls=(f"{gateway.url}/api/v1/captures",)) == []


def test_missing_asset_shows_the_api_message(browsers: Browsers, gateway: LiveGateway) -> None:
    missing = "0" * 32
    with viewer_page(browsers, "webgl2", gateway.key) as (page, log):
        page.goto(f"{gateway.url}/?asset={missing}")
        assert wait_state(page) == "error"
        detail = httpx.get(f"{gateway.url}/api/v1/assets/{missing}/mesh.glb",
                           headers=gateway.auth).json()["detail"]
        assert page.inner_text("#message").strip() == detail
        assert log.errors(allowed_urls=(f"{gateway.url}/api/v1/assets/{missing}/",)) == []


def test_upload_through_the_page_runs_to_a_rendered_mesh(
        browsers: Browsers, gateway: LiveGateway, tmp_path: Path, artifacts: Path) -> None:
    capture = synthetic_capture_zip(tmp_path, seed=1)  # not the `job` fixture's capture
    with viewer_page(browsers, "webgpu") as (page, log):
        page.goto(gateway.url + "/")
        assert wait_state(page) == "ready", page.inner_text("#message")
        assert page.is_visible("#hint")
        page.fill("#api-key", gateway.key)
        page.click("#api-key-form button")
        page.uncheck("#enhance")
        page.set_input_files("#file", str(capture))
        page.wait_for_function("['done', 'error'].includes(document.body.dataset.upload)",
                               timeout=100_000)
        assert page.evaluate("document.body.dataset.upload") == "done", \
            page.inner_text("#message")
        stats = page.evaluate("window.viewerStats")
        assert stats["job"]["state"] == "succeeded"
        assert stats["job"]["updates"] >= 3  # queued/running/... pushed live, not one poll
        asset = httpx.get(f"{gateway.url}/api/v1/jobs/{stats['job']['id']}",
                          headers=gateway.auth).json()["asset_id"]
        assert page.evaluate("location.search") == f"?asset={asset}"
        report = httpx.get(f"{gateway.url}/api/v1/assets/{asset}/report.json",
                           headers=gateway.auth).json()
        assert stats["triangles"] == report["triangles"] > 1000
        _settle(page)
        pixels = viewport_pixels(page, artifacts / "upload-result.png")
        assert 0.03 < foreground(pixels).mean() < 0.6
        assert not page.is_visible("#hint")
        assert page.locator("#jobs a").count() >= 1
        assert log.errors() == []


def test_a_share_link_shows_the_asset_to_a_viewer_with_no_key(
        browsers: Browsers, gateway: LiveGateway, torus_asset: str) -> None:
    with viewer_page(browsers, "webgl2", gateway.key) as (page, log):
        page.goto(f"{gateway.url}/?asset={torus_asset}")
        assert wait_state(page) == "ready", page.inner_text("#message")
        page.click("#share")
        page.wait_for_function("document.getElementById('share-url').value !== ''")
        link = page.input_value("#share-url")
        owner_view = page.evaluate("window.viewerStats")
        assert log.errors() == []
    assert link.startswith(f"{gateway.url}/?asset={torus_asset}&share=")
    with viewer_page(browsers, "webgl2") as (page, log):
        page.goto(link)
        assert wait_state(page) == "ready", page.inner_text("#message")
        shared_view = page.evaluate("window.viewerStats")
        assert shared_view["triangles"] == owner_view["triangles"] > 50_000
        assert page.is_hidden("#share-section")  # no key: nothing to share with
        assert log.errors() == []
        # Without the token the same page has no access.
        page.goto(f"{gateway.url}/?asset={torus_asset}")
        assert wait_state(page) == "error"
        assert "API key" in page.inner_text("#message")
