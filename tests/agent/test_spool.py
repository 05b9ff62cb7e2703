"""The spool: frame-sets whole or absent after a kill, sent oldest first, bounded in size,
and a state that says where a resumed run goes on."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
import time
from dataclasses import asdict, replace
from pathlib import Path

import pytest

from agent.spool import Spool, SpoolState

ROOT = Path(__file__).resolve().parents[2]
STATE = SpoolState(gateway_url="http://gateway", stream_id="s1", source="synthetic",
                   depth_scale=0.001, cameras=({"id": "cam0"},))
NEVER = threading.Event()


def _put(spool: Spool, index: int, size: int = 100) -> None:
    assert spool.put(index, 1000 * index, bytes([index % 256]) * size, wait=False, stop=NEVER)


def test_frame_sets_go_oldest_first_and_one_sender_each(tmp_path: Path) -> None:
    spool = Spool(tmp_path, max_bytes=10**9)
    for index in (3, 1, 2):
        _put(spool, index)
    first, second = spool.take(0.1), spool.take(0.1)
    assert first is not None and second is not None
    assert (first.index, first.timestamp_us, second.index) == (1, 1000, 2)
    assert first.path.read_bytes() == bytes([1]) * 100
    spool.acknowledge(first)
    assert not first.path.exists() and spool.size() == (2, 200)
    third = spool.take(0.1)
    assert third is not None and third.index == 3
    assert spool.take(0.05) is None  # every frame-set held by a sender
    rejected = spool.reject(second)
    assert rejected.parent == tmp_path / "rejected" and rejected.read_bytes() == bytes([2]) * 100
    assert spool.size() == (1, 100)
    assert not list((tmp_path / "frames").glob(".*"))  # no temporary files left


def test_a_new_spool_object_finds_the_frame_sets_and_the_state(tmp_path: Path) -> None:
    spool = Spool(tmp_path, max_bytes=10**9)
    assert spool.read_state() is None
    for index in range(4):
        _put(spool, index)
    spool.write_state(STATE.advanced(0).advanced(1).advanced(2))
    again = Spool(tmp_path, max_bytes=10**9)
    state = again.read_state()
    assert state == SpoolState(**{**STATE.__dict__, "next_index": 3, "next_position": 3})
    assert again.size() == (4, 400)
    # Frame-set 3 was spooled but its state never written: captured again on resume.
    assert again.drop_from(state.next_index) == 1 and again.size() == (3, 300)
    again.clear_state()
    assert again.read_state() is None


def test_a_full_spool_makes_a_replay_wait_and_a_live_source_drop(tmp_path: Path) -> None:
    spool = Spool(tmp_path, max_bytes=250)
    _put(spool, 0)
    _put(spool, 1)
    assert spool.full() is False
    assert not spool.put(2, 0, b"x" * 100, wait=False, stop=NEVER)  # live: dropped
    done: list[bool] = []
    waiter = threading.Thread(target=lambda: done.append(
        spool.put(2, 0, b"x" * 100, wait=True, stop=NEVER)))
    waiter.start()
    time.sleep(0.3)
    assert not done  # a replay waits for room
    entry = spool.take(0.1)
    assert entry is not None
    spool.acknowledge(entry)
    waiter.join(5)
    assert done == [True] and spool.size() == (2, 200)


def test_one_frame_set_larger_than_the_cap_still_goes_into_an_empty_spool(
        tmp_path: Path) -> None:
    spool = Spool(tmp_path, max_bytes=10)
    assert spool.put(0, 0, b"y" * 100, wait=False, stop=NEVER)
    assert spool.full()


def test_the_state_file_is_the_whole_state_each_time(tmp_path: Path) -> None:
    # The unchanging fields are encoded once: a changed camera or stream still shows.
    spool = Spool(tmp_path, max_bytes=10)
    for state in (STATE, STATE.advanced(4), replace(STATE, cameras=({"id": "cam1"},)),
                  replace(STATE, stream_id="s2", source_done=True)):
        spool.write_state(state)
        written = json.loads((tmp_path / "state.json").read_text())
        assert written == {**asdict(state), "cameras": list(state.cameras)}
        assert Spool(tmp_path, max_bytes=10).read_state() == state


def test_an_unreadable_state_is_one_line_saying_what_to_do(tmp_path: Path) -> None:
    Spool(tmp_path, max_bytes=10)
    (tmp_path / "state.json").write_text("{not json")
    with pytest.raises(ValueError, match="delete the folder"):
        Spool(tmp_path, max_bytes=10).read_state()


WRITER = """
import sys, threading
from dataclasses import asdict, replace
from pathlib import Path
from agent.spool import Spool, SpoolState
spool = Spool(Path(sys.argv[1]), 10**12)
state = SpoolState("http://gateway", "s1", "synthetic", 0.001, ())
print("ready", flush=True)
for index in range(40):
    spool.put(index, index, bytes([index]) * 3_000_000, wait=True, stop=threading.Event())
    state = state.advanced(index)
    spool.write_state(state)
"""


@pytest.mark.parametrize("delay_s", [0.05, 0.2, 0.45])
def test_a_kill_mid_write_leaves_whole_frame_sets_and_a_resumable_state(
        tmp_path: Path, delay_s: float) -> None:
    writer = subprocess.Popen([sys.executable, "-c", WRITER, str(tmp_path)], cwd=ROOT,
                              stdout=subprocess.PIPE, text=True)
    assert writer.stdout is not None and writer.stdout.readline().strip() == "ready"
    time.sleep(delay_s)
    writer.send_signal(signal.SIGKILL)
    writer.wait(10)
    spool = Spool(tmp_path, max_bytes=10**12)  # removes a write the kill cut short
    files = sorted((tmp_path / "frames").iterdir())
    assert all(not f.name.startswith(".") for f in files)
    for file in files:
        index = int(file.name[:6])
        assert file.read_bytes() == bytes([index]) * 3_000_000  # whole, never partial
    state = spool.read_state()
    recorded = state.next_index if state is not None else 0
    spool.drop_from(recorded)
    assert sorted(int(f.name[:6]) for f in (tmp_path / "frames").iterdir()) == \
        list(range(recorded))
    assert state is None or state.next_position == recorded
