"""The viewer plays a sequence the service reconstructed: its served sequence.json with the
viewer's key, and the same sequence through a share link with no key."""

from __future__ import annotations

import urllib.parse
from pathlib import Path
from typing import Any

import httpx
import pytest

from tests.integration.services import FAST_JOB, sequence_capture_zip
from tests.web.harness import Browsers, LiveGateway, viewer_page, wait_state

pytestmark = pytest.mark.timeout(240)
FRAMES = 3


@pytest.fixture(scope="module")
def sequence(gateway: LiveGateway, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    capture = sequence_capture_zip(tmp_path_factory.mktemp("sequence"), frames=FRAMES)
    finished = gateway.run_job(capture, timeout_s=200, frames="all", **FAST_JOB)
    assert finished["state"] == "succeeded", finished
    assert finished["frames_done"] == FRAMES
    return finished


def _play(page: Any) -> None:
    assert wait_state(page) == "ready", page.inner_text("#message")
    assert page.is_visible("#sequence-bar")
    assert page.inner_text("#frame-label") == f"1 / {FRAMES}"
    page.click("#play")
    page.wait_for_function(f"window.viewerStats.sequence.shown >= {FRAMES + 2}",
                           timeout=30_000)  # every frame shown, and looped


def test_the_served_sequence_plays_with_the_key(browsers: Browsers, gateway: LiveGateway,
                                                sequence: dict[str, Any],
                                                artifacts: Path) -> None:
    manifest = sequence["links"]["sequence"]
    assert sequence["links"]["viewer"] == f"/?sequence={manifest}"
    with viewer_page(browsers, "webgl2", gateway.key) as (page, log):
        page.goto(f"{gateway.url}/?sequence={urllib.parse.quote(manifest, safe='/')}")
        _play(page)
        page.locator("#viewport").screenshot(path=str(artifacts / "sequence-job.png"))
        assert log.errors() == []
    with viewer_page(browsers, "webgl2") as (page, log):  # no key: the API's own message
        page.goto(f"{gateway.url}/?sequence={urllib.parse.quote(manifest, safe='/')}")
        assert wait_state(page) == "error"
        assert "API key" in page.inner_text("#message")


def test_a_share_link_plays_the_sequence_with_no_key(browsers: Browsers, gateway: LiveGateway,
                                                     sequence: dict[str, Any]) -> None:
    shared = httpx.post(f"{gateway.url}/api/v1/assets/{sequence['asset_id']}/share",
                        headers=gateway.auth, json={"expires_in_s": 600}, timeout=30)
    assert shared.status_code == 201, shared.text
    with viewer_page(browsers, "webgl2") as (page, log):
        page.goto(gateway.url + shared.json()["viewer_url"])
        _play(page)
        assert log.errors() == []
