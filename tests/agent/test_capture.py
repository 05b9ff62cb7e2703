"""The capture loop on real sources, without a gateway: frame-sets spooled under consecutive
indices with the state after each, previews at their rate (beside the spool), a live source
dropping when the spool is full, a replay paced by its timestamps."""

from __future__ import annotations

import io
import threading
import time
import zipfile
from dataclasses import replace
from pathlib import Path

import pytest

from agent.capture import CaptureSettings, posed, run_capture
from agent.preview import decode_preview
from agent.sources import open_source
from agent.spool import Spool, SpoolState
from agent.stats import Stats
from tests.integration.services import sequence_capture_zip

STATE = SpoolState(gateway_url="http://gateway", stream_id="s1", source="capture:x",
                   depth_scale=0.001, cameras=())


@pytest.fixture(scope="module")
def capture_zip(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Four posed cameras of 160x144, 8 frames at 10 fps."""
    return sequence_capture_zip(tmp_path_factory.mktemp("capture"), frames=8, fps=10.0)


def _zips(spool: Path) -> dict[int, zipfile.ZipFile]:
    return {int(p.name[:6]): zipfile.ZipFile(io.BytesIO(p.read_bytes()))
            for p in sorted((spool / "frames").glob("*.zip"))}


def test_a_replay_spools_every_frame_set_with_previews_at_their_rate(
        capture_zip: Path, tmp_path: Path) -> None:
    source = open_source(f"capture:{capture_zip}")
    spool, stats = Spool(tmp_path, 10**9), Stats()
    settings = CaptureSettings(fast=True, preview_hz=5.0,
                               posed_cameras=posed(source.info.cameras, source.info.cameras))
    previews: list[bytes] = []
    state = run_capture(source, spool, replace(STATE, next_index=20, next_position=3),
                        settings, stats, threading.Event(), previews.append)
    source.close()
    assert (state.next_index, state.next_position, state.source_done) == (25, 8, True)
    assert spool.read_state() == state
    zips = _zips(tmp_path)
    assert sorted(zips) == [20, 21, 22, 23, 24]  # positions 3..7 under the next indices
    decoded = [decode_preview(data) for data in previews]
    # One in each 200 ms of device time (5 Hz): frames at 0.3 s (the first), 0.4 s, 0.6 s.
    assert [preview.frame_index for preview in decoded] == [20, 21, 23]
    assert all(len(preview.positions_m) > 1000 for preview in decoded)
    assert not any("preview.bin" in z.namelist() for z in zips.values())  # never spooled
    assert all(n.endswith("/000022.png") or n.endswith("/000022.jpg")
               for n in zips[22].namelist())
    assert stats.snapshot(0, 0, 0).captured == 5


def test_without_poses_there_is_no_preview(capture_zip: Path, tmp_path: Path) -> None:
    source = open_source(f"capture:{capture_zip}")
    unposed = tuple(replace(c, world_from_depth=None) for c in source.info.cameras)
    assert posed(source.info.cameras, unposed) is None
    spool = Spool(tmp_path, 10**9)
    previews: list[bytes] = []
    run_capture(source, spool, STATE, CaptureSettings(fast=True), Stats(), threading.Event(),
                previews.append)
    assert previews == [] and _zips(tmp_path)


def test_a_live_source_drops_frame_sets_while_the_spool_is_full(capture_zip: Path,
                                                                tmp_path: Path) -> None:
    source = open_source(f"capture:{capture_zip}")
    source.info = replace(source.info, live=True)  # the same frames, as a device gives them
    spool, stats = Spool(tmp_path, max_bytes=1), Stats()
    state = run_capture(source, spool, STATE, CaptureSettings(), stats, threading.Event())
    snapshot = stats.snapshot(0, 0, 0)
    assert (snapshot.captured, snapshot.dropped) == (1, 7)  # nobody empties the spool
    assert sorted(_zips(tmp_path)) == [0] and state.next_index == 1


def test_a_replay_keeps_its_frame_rate_unless_fast_and_stops_when_asked(
        capture_zip: Path, tmp_path: Path) -> None:
    source = open_source(f"capture:{capture_zip}")
    stop = threading.Event()
    started = time.monotonic()
    state = run_capture(source, Spool(tmp_path / "a", 10**9), STATE, CaptureSettings(),
                        Stats(), stop)
    assert time.monotonic() - started >= 0.65  # 8 frames at 10 fps: 0.7 s after the first
    assert state.source_done
    stop.set()
    stopped = run_capture(source, Spool(tmp_path / "b", 10**9), STATE,
                          CaptureSettings(fast=True), Stats(), stop)
    assert stopped == STATE  # nothing captured, the source not done
