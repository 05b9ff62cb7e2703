"""The edge agent against a real `volumesh serve`, both as separate processes: the gateway
killed for seconds in the middle of a 300-frame stream, and the agent killed and started again.
Either way every frame-set of the source arrives exactly once, in order, and the stream closes
into a capture that holds them all. And a viewer's socket gets the agent's previews while the
frame-sets are captured."""

from __future__ import annotations

import json
import signal
import struct
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import pytest

from tests.integration.services import Process, base_env, free_port, wait_for
from tests.stream_sources import replay_capture

pytestmark = pytest.mark.slow
FRAMES = 300
FPS = 30.0


def _serve(data_dir: Path, port: int, log: Path) -> Process:
    serve = Process([sys.executable, "-m", "app", "serve", "--port", str(port), "--data-dir",
                     str(data_dir)], base_env(), log).start()
    wait_for(lambda: httpx.get(f"http://127.0.0.1:{port}/readyz", timeout=1).status_code == 200,
             90, f"serve ready\n{serve.tail()}", interval_s=0.2)
    return serve


@dataclass
class Served:
    """`volumesh serve` on its own data folder, and a client with its API key."""

    data_dir: Path
    port: int
    serve: Process
    key: str
    client: httpx.Client

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def restart(self) -> None:
        self.serve = _serve(self.data_dir, self.port, self.serve.log)


def _start(tmp_path: Path) -> Served:
    data_dir, port = tmp_path / "data", free_port()
    serve = _serve(data_dir, port, tmp_path / "serve.log")
    key = (data_dir / "api-key.txt").read_text().strip()
    client = httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=30,
                          headers={"Authorization": f"Bearer {key}"})
    return Served(data_dir, port, serve, key, client)


@pytest.fixture(scope="module")
def shared(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    """One `volumesh serve` for the tests that leave it running; each finds its own stream
    among those of the tests before it (a capture of other bytes, so none is another's)."""
    served = _start(tmp_path_factory.mktemp("served"))
    try:
        yield served
    finally:
        served.client.close()
        # SIGKILL: its embedded workers get their SIGTERM from the kernel (PR_SET_PDEATHSIG),
        # as on any kill; a graceful stop takes seconds and is test_embedded.py's to check.
        served.serve.kill()


def _agent(url: str, key: str, capture: Path, spool: Path, log: Path) -> Process:
    return Process([sys.executable, "-m", "app", "agent", "--gateway", url, "--key", key,
                    "--source", f"capture:{capture}", "--spool", str(spool)],
                   base_env(), log).start()


def _stored_frames(client: httpx.Client, stream_id: str) -> int:
    return int(client.get(f"/api/v1/streams/{stream_id}").json()["frames_received"])


def _stream_ids(client: httpx.Client) -> set[str]:
    return {str(item["id"]) for item in client.get("/api/v1/streams").json()["items"]}


def _only_stream(client: httpx.Client, before: frozenset[str] = frozenset()) -> str:
    """The one stream of the gateway beside those in ``before`` (a test's start)."""
    items = [s for s in client.get("/api/v1/streams").json()["items"] if s["id"] not in before]
    assert len(items) == 1, items
    return str(items[0]["id"])


def _check_capture(client: httpx.Client, stream_id: str, data_dir: Path) -> None:
    """The stream closed into a capture with every source frame once, timestamps in order."""
    import zipfile

    stream = wait_for(lambda: (s := client.get(f"/api/v1/streams/{stream_id}").json())["state"]
                      in ("closed", "failed") and s, 120, "the stream to close")
    assert stream["state"] == "closed", stream
    assert stream["frames_received"] == FRAMES
    capture = client.get(f"/api/v1/captures/{stream['capture_id']}").json()
    assert capture["frames"] == FRAMES
    (zip_path,) = (data_dir / "storage" / "captures").glob(f"{capture['sha256']}-*.zip")
    with zipfile.ZipFile(zip_path) as archive:
        frames = json.loads(archive.read("capture.json"))["frames"]
        depth = [n for n in archive.namelist() if "/depth/" in n]
    assert [f["index"] for f in frames] == list(range(FRAMES))
    assert [f["timestamp_us"] for f in frames] == [round(i * 1e6 / FPS) for i in range(FRAMES)]
    assert len(depth) == 2 * FRAMES


def test_a_gateway_down_for_ten_seconds_loses_and_repeats_nothing(tmp_path: Path) -> None:
    capture = replay_capture(tmp_path, FRAMES, FPS)
    served = _start(tmp_path)
    client = served.client
    agent = _agent(served.url, served.key, capture, tmp_path / "spool", tmp_path / "agent.log")
    try:
        stream_id = wait_for(lambda: _only_stream(client), 30, "the agent's stream")
        wait_for(lambda: _stored_frames(client, stream_id) >= 60, 30, "60 frame-sets")
        served.serve.kill()
        time.sleep(10.0)
        assert agent.alive, agent.tail()
        # Capture went on into the spool while nobody took the frame-sets.
        assert len(list((tmp_path / "spool" / "frames").glob("*.zip"))) > 30
        served.restart()
        assert agent.proc is not None
        assert agent.proc.wait(120) == 0, agent.tail()
        _check_capture(client, stream_id, served.data_dir)
        log = agent.log.read_text()
        assert "gateway away" in log and "gateway back" in log, log
    finally:
        agent.stop()
        served.client.close()
        served.serve.kill()  # as `shared` is stopped


def test_a_killed_agent_resumes_its_spool(shared: Served, tmp_path: Path) -> None:
    capture = replay_capture(tmp_path, FRAMES, FPS)
    served = shared
    client, url, key = served.client, served.url, served.key
    before = frozenset(_stream_ids(client))
    spool = tmp_path / "spool"
    agent = _agent(url, key, capture, spool, tmp_path / "agent-1.log")
    try:
        stream_id = wait_for(lambda: _only_stream(client, before), 30, "the agent's stream")
        wait_for(lambda: _stored_frames(client, stream_id) >= 100, 30, "100 frame-sets")
        agent.kill(signal.SIGKILL)
        stored_at_kill = _stored_frames(client, stream_id)
        assert stored_at_kill < FRAMES
        agent = _agent(url, key, capture, spool, tmp_path / "agent-2.log")
        assert agent.proc is not None
        assert agent.proc.wait(120) == 0, agent.tail()
        assert _only_stream(client, before) == stream_id  # resumed, not a second stream
        _check_capture(client, stream_id, served.data_dir)
    finally:
        agent.stop()


def test_a_viewer_sees_the_agents_previews_as_they_are_captured(shared: Served,
                                                                tmp_path: Path) -> None:
    """Previews go beside the frame-sets: each reaches the viewer's socket soon after its
    frame-set was captured, in capture order."""
    from websockets.sync.client import connect

    frames = 150  # 5 s at 30 fps: 50 previews at the default 10 Hz
    capture = replay_capture(tmp_path, frames, FPS)
    served = shared
    client, url, key = served.client, served.url, served.key
    before = frozenset(_stream_ids(client))
    agent = _agent(url, key, capture, tmp_path / "spool", tmp_path / "agent.log")
    previews: list[tuple[int, float]] = []  # frame index, age at arrival (s)
    try:
        stream_id = wait_for(lambda: _only_stream(client, before), 30, "the agent's stream")
        socket_url = url.replace("http", "ws") + f"/api/v1/streams/{stream_id}/preview"
        with connect(socket_url, max_size=None, open_timeout=10) as socket:
            socket.send(json.dumps({"key": key}))
            for message in socket:
                if isinstance(message, str):
                    break  # the stream stopped receiving
                (length,) = struct.unpack_from("<I", message)
                header = json.loads(message[4:4 + length])
                previews.append((header["frame_index"], time.time() - header["captured_at"]))
        assert agent.proc is not None
        assert agent.proc.wait(120) == 0, agent.tail()
    finally:
        agent.stop()
    indices = [index for index, _ in previews]
    assert len(previews) >= 10, previews  # of 50 made, most while the socket was open
    assert indices == sorted(set(indices))
    assert max(age for _, age in previews) < 2.0, previews
