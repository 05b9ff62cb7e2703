"""`volumesh agent` against a real gateway and worker (separate processes): every frame-set
arrives exactly once and the stream closes into a capture with every frame, through an
interrupted agent resumed from its spool; frame-sets refused are set aside. (A gateway killed
mid-stream: tests/integration/test_agent_stream.py.)"""

from __future__ import annotations

import json
import signal
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import numpy as np
import pytest

from pipeline.io.capture_io import open_capture
from tests.integration.services import (
    Gateway,
    Process,
    base_env,
    create_key,
    sequence_capture_zip,
    stop_all,
    wait_for,
    wait_worker_ready,
    worker,
)

pytestmark = pytest.mark.slow


@dataclass
class Service:
    gateway: Gateway
    env: dict[str, str]
    key: str
    data_dir: Path
    client: httpx.Client


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Service]:
    folder = tmp_path_factory.mktemp("agent-service")
    env = base_env(data_dir=str(folder / "data"))
    validate = worker(env, folder / "worker.log", queues="validate").start()
    gateway = Gateway(env, folder / "gateway.log").start()
    key = create_key(env)
    wait_worker_ready(validate)
    client = httpx.Client(base_url=gateway.url + "/api/v1", timeout=30,
                          headers={"Authorization": f"Bearer {key}"})
    yield Service(gateway, env, key, folder / "data", client)
    client.close()
    stop_all([gateway, validate])


def _agent(service: Service, log: Path, *args: str) -> Process:
    return Process([sys.executable, "-m", "app", "agent", "--gateway", service.gateway.url,
                    *args], {**service.env, "VOLUMESH_API_KEY": service.key}, log).start()


def _finished(agent: Process, timeout_s: float) -> int:
    assert agent.proc is not None
    return agent.proc.wait(timeout_s)


def _stream_id(spool: Path) -> str:
    return str(json.loads((spool / "state.json").read_text())["stream_id"])


def _check_capture(service: Service, agent_log: Path, frames: int, period_us: int) -> None:
    """The agent printed a capture of ``frames`` frames, each index once, as its stream
    received them; the spool is empty."""
    output = agent_log.read_text()
    line = next(x for x in output.splitlines() if x.startswith("capture "))
    capture_id = line.split()[1].rstrip(":")
    assert f"{frames} frame-set(s)" in line
    assert "next: curl -X POST" in output and capture_id in output
    stream_id = line.split("from stream ")[1].strip()
    stream = service.client.get(f"/streams/{stream_id}").json()
    assert (stream["state"], stream["capture_id"]) == ("closed", capture_id)
    assert (stream["frames_received"], stream["last_frame_index"]) == (frames, frames - 1)
    capture = service.client.get(f"/captures/{capture_id}").json()
    assert (capture["state"], capture["frames"]) == ("ready", frames)
    stored = next((service.data_dir / "storage" / "captures").glob(f"{capture_id}*.zip"))
    with open_capture(stored) as reader:
        assert reader.meta.frame_indices == tuple(range(frames))
        intervals_us = np.diff([f.timestamp_us for f in reader.meta.frames])
        assert np.abs(intervals_us - period_us).max() <= 1


SYNTHETIC_FRAMES = 3
"""Frame-sets of the synthetic rig's stream (two intervals to check): each takes the rig
seconds to render (eight 640x576 cameras)."""


def test_a_synthetic_stream_arrives_whole_and_becomes_a_capture(service: Service,
                                                                tmp_path: Path) -> None:
    log, spool = tmp_path / "agent.log", tmp_path / "spool"
    agent = _agent(service, log, "--source", "synthetic", "--frames", str(SYNTHETIC_FRAMES),
                   "--fast", "--spool", str(spool))
    assert _finished(agent, 300) == 0, agent.tail()
    _check_capture(service, log, SYNTHETIC_FRAMES, 33_333)
    assert not (spool / "state.json").exists() and not list((spool / "frames").iterdir())


@pytest.fixture(scope="module")
def replayed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The 40-frame capture the replay tests' agents read (made once: seconds to render)."""
    return sequence_capture_zip(tmp_path_factory.mktemp("replayed"), frames=40, fps=10.0)


def _replay(replayed: Path, tmp_path: Path) -> tuple[list[str], Path]:
    spool = tmp_path / "spool"
    return ["--source", f"capture:{replayed}", "--spool", str(spool)], spool


def test_an_agent_stopped_mid_stream_resumes_the_same_stream_from_its_spool(
        service: Service, replayed: Path, tmp_path: Path) -> None:
    args, spool = _replay(replayed, tmp_path)
    first = _agent(service, tmp_path / "first.log", *args)
    wait_for(lambda: (spool / "state.json").is_file() and json.loads(
        (spool / "state.json").read_text())["next_index"] >= 10, 60, "10 frame-sets spooled")
    stream_id = _stream_id(spool)
    first.stop(grace_s=20)  # SIGTERM: stop capturing, keep the spool
    assert first.proc is not None and first.proc.returncode == 128 + signal.SIGTERM
    assert "run the same command to resume" in first.log.read_text()
    stopped_at = json.loads((spool / "state.json").read_text())["next_index"]
    assert 10 <= stopped_at < 40
    second = _agent(service, tmp_path / "second.log", *args)
    assert _finished(second, 120) == 0, second.tail()
    assert f"from stream {stream_id}" in second.log.read_text()
    _check_capture(service, tmp_path / "second.log", 40, 100_000)


def test_frame_sets_the_gateway_refuses_are_set_aside_with_a_line_each(
        service: Service, replayed: Path, tmp_path: Path) -> None:
    args, spool = _replay(replayed, tmp_path)
    agent = _agent(service, tmp_path / "agent.log", *args)
    wait_for(lambda: (spool / "state.json").is_file(), 60, "the stream")
    stream_id = _stream_id(spool)
    wait_for(lambda: service.client.get(f"/streams/{stream_id}").json()["frames_received"] >= 5,
             60, "5 frame-sets received")
    closed = service.client.post(f"/streams/{stream_id}/close")  # by someone else
    assert closed.status_code == 202, closed.text
    assert _finished(agent, 120) == 0, agent.tail()
    output = agent.log.read_text()
    rejected = sorted((spool / "rejected").iterdir())
    received = service.client.get(f"/streams/{stream_id}").json()["frames_received"]
    assert len(rejected) == 40 - received and rejected  # 409: the stream took no more
    assert output.count("refused (409") == len(rejected)
    assert f"{len(rejected)} frame-set(s) refused by the gateway" in output
    assert "capture " in output and not list((spool / "frames").iterdir())
