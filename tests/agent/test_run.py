"""The agent's run without a gateway to talk to: a new stream needs one (a readable refusal
after the deadline); a resumed one captures on into the spool while the gateway is away."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import pytest

from agent.run import AgentConfig, cameras_json, run_agent
from agent.sources import open_source
from agent.spool import Spool, SpoolState
from tests.integration.services import free_port, sequence_capture_zip


@pytest.fixture(scope="module")
def capture_zip(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return sequence_capture_zip(tmp_path_factory.mktemp("capture"), frames=8, fps=10.0)


def _away() -> str:
    return f"http://127.0.0.1:{free_port()}"  # nothing listens there


def test_a_new_stream_with_the_gateway_away_is_refused_after_the_deadline(
        capture_zip: Path, tmp_path: Path) -> None:
    config = AgentConfig(gateway_url=_away(), api_key="k", source=f"capture:{capture_zip}",
                         spool_dir=tmp_path, connect_deadline_s=0.5)
    started = time.monotonic()
    with pytest.raises(ValueError, match=r"--gateway: no answer from .* in 0.5 s"):
        run_agent(config, threading.Event())
    assert time.monotonic() - started < 10
    assert Spool(tmp_path, 1).read_state() is None  # no stream, nothing to resume


def test_a_resumed_stream_captures_into_the_spool_while_the_gateway_is_away(
        capture_zip: Path, tmp_path: Path) -> None:
    url, source = _away(), f"capture:{capture_zip}"
    opened = open_source(source)
    spool = Spool(tmp_path, 10**9)
    spool.write_state(SpoolState(url, "st1", source, opened.info.depth_scale,
                                 tuple(cameras_json(opened.info.depth_scale,
                                                    opened.info.cameras)),
                                 next_index=5, next_position=2))
    opened.close()
    (tmp_path / "frames" / "000005-0.zip").write_bytes(b"never recorded in the state")
    stop = threading.Event()
    config = AgentConfig(gateway_url=url, api_key="k", source=source, spool_dir=tmp_path,
                         fast=True)
    results: list[object] = []
    runner = threading.Thread(target=lambda: results.append(run_agent(config, stop)))
    runner.start()
    state_file = tmp_path / "state.json"
    deadline = time.monotonic() + 60
    while not json.loads(state_file.read_text())["source_done"]:
        assert time.monotonic() < deadline, "the source was not captured"
        time.sleep(0.05)
    stop.set()
    runner.join(30)
    assert [getattr(r, "state", None) for r in results] == ["interrupted"]
    state = json.loads(state_file.read_text())
    assert (state["next_index"], state["next_position"]) == (11, 8)
    names = sorted(p.name[:6] for p in (tmp_path / "frames").glob("*.zip"))
    assert names == [f"{i:06d}" for i in range(5, 11)]  # positions 2..7, none twice
    assert (tmp_path / "frames" / "000005-200000.zip").is_file()  # captured again, whole
