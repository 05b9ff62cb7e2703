"""The viewer's live preview in Debian's Chromium: frame-sets and their previews PUT at 5 Hz to a
live gateway show as a point cloud that keeps updating, and the stream's close shows its
capture."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from agent.preview import pack_preview
from tests.live_streams import frame_set, stream_body
from tests.web.harness import (
    Browsers,
    LiveGateway,
    foreground,
    viewer_page,
    viewport_pixels,
    wait_state,
)

pytestmark = pytest.mark.timeout(180)

POINTS = 40_000
RED = (230, 40, 40)


def red_sphere_preview(index: int) -> bytes:
    """A red sphere of points 0.3 m across at (0, 1, 0), a little turned each frame."""
    rng = np.random.default_rng(index)
    directions = rng.normal(size=(POINTS, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    positions_m = (0.3 * directions + [0.0, 1.0, 0.0]).astype(np.float32)
    colors = np.tile(np.array(RED, np.uint8), (POINTS, 1))
    return pack_preview(index, time.time(), positions_m, colors)


class Sender(threading.Thread):
    """PUTs frame-sets and their previews at 5 Hz, as an agent does, until stopped."""

    def __init__(self, gateway: LiveGateway, stream_id: str) -> None:
        super().__init__(name="live-sender", daemon=True)
        self.gateway, self.stream_id = gateway, stream_id
        self.stop = threading.Event()
        self.sent = 0
        self.failures: list[str] = []

    def run(self) -> None:
        with httpx.Client(base_url=self.gateway.url, headers=self.gateway.auth,
                          timeout=30) as client:
            while not self.stop.is_set():
                started = time.monotonic()
                answer = client.put(f"/api/v1/streams/{self.stream_id}/frames/{self.sent}",
                                    content=frame_set(self.sent),
                                    headers={"Content-Type": "application/zip"})
                preview = client.put(f"/api/v1/streams/{self.stream_id}/preview",
                                     content=red_sphere_preview(self.sent),
                                     headers={"Content-Type": "application/octet-stream"})
                if (answer.status_code, preview.status_code) != (201, 204):
                    self.failures.append(answer.text + preview.text)
                    return
                self.sent += 1
                self.stop.wait(max(0.0, 0.2 - (time.monotonic() - started)))


def test_live_preview_updates_and_shows_the_close(browsers: Browsers, gateway: LiveGateway,
                                                  artifacts: Path) -> None:
    created = httpx.post(f"{gateway.url}/api/v1/streams", json=stream_body("web live"),
                         headers=gateway.auth)
    assert created.status_code == 201, created.text
    stream_id = created.json()["id"]
    sender = Sender(gateway, stream_id)
    with viewer_page(browsers, "webgpu", gateway.key) as (page, log):
        # The panel lists the key's receiving streams, each linking to its live view.
        page.goto(gateway.url + "/")
        assert wait_state(page) == "ready", page.inner_text("#message")
        page.wait_for_selector(f"#streams a[href='/?live={stream_id}']")

        page.goto(f"{gateway.url}/?live={stream_id}")
        assert wait_state(page) == "ready", page.inner_text("#message")
        sender.start()
        try:
            page.wait_for_function("window.viewerStats.live.updates >= 8", timeout=30_000)
            # Both at once: the next preview may arrive between two reads.
            live, status = page.evaluate("[{...window.viewerStats.live}, "
                                         "document.getElementById('live-status').textContent]")
            page.evaluate("new Promise(r => requestAnimationFrame(() => "
                          "requestAnimationFrame(r)))")
            pixels = viewport_pixels(page, artifacts / "live-preview.png")
        finally:
            sender.stop.set()
            sender.join(30)
        assert sender.failures == []
        assert live["points"] == POINTS
        assert live["frameIndex"] >= 7
        assert 2 < live["rate"] < 8, live  # about the sender's 5 Hz
        assert 0 <= live["ageMs"] < 2000, live
        assert f"frame {live['frameIndex']}" in status and "updates/s" in status
        assert "40,000 points" in status and "age" in status
        mask = foreground(pixels)
        assert 0.01 < mask.mean() < 0.6, f"{mask.mean():.2%} of the view is points"
        drawn = pixels[mask]
        assert drawn[:, 0].mean() > drawn[:, 1].mean() + 60  # the points' own red

        closed = httpx.post(f"{gateway.url}/api/v1/streams/{stream_id}/close",
                            headers=gateway.auth)
        assert closed.status_code == 202, closed.text
        page.wait_for_function("window.viewerStats.live.closed === 'closed'", timeout=60_000)
        capture_id = httpx.get(f"{gateway.url}/api/v1/streams/{stream_id}",
                               headers=gateway.auth).json()["capture_id"]
        assert "closed" in page.inner_text("#live-status")
        assert capture_id[:12] in page.inner_text("#live-status")
        page.click("#live-reconstruct")  # every frame of the capture, as one sequence job
        page.wait_for_function(
            "document.querySelector('#live-status').textContent.includes('queued')",
            timeout=30_000)
        jobs = httpx.get(f"{gateway.url}/api/v1/jobs", headers=gateway.auth).json()["items"]
        assert [(job["capture_id"], job["frames_total"]) for job in jobs] == [
            (capture_id, sender.sent)], jobs
        assert log.errors() == []
    # Queued was all this test asks of the job: cancelled, its frames leave the session's one
    # worker to the jobs of the tests after this one.
    cancelled = httpx.delete(f"{gateway.url}/api/v1/jobs/{jobs[0]['id']}", headers=gateway.auth)
    assert cancelled.status_code == 200, cancelled.text


def test_live_preview_without_a_key_says_so(browsers: Browsers, gateway: LiveGateway
                                            ) -> None:
    created = httpx.post(f"{gateway.url}/api/v1/streams", json=stream_body("no key"),
                         headers=gateway.auth)
    with viewer_page(browsers, "webgl2") as (page, log):
        page.goto(f"{gateway.url}/?live={created.json()['id']}")
        page.wait_for_function("window.viewerStats.live?.closed === 'unauthorized'",
                               timeout=20_000)
        assert "API key" in page.inner_text("#message")
        assert log.errors() == []
