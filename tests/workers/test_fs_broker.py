"""The embedded broker never hands a worker a half-written message (kombu's own file-system
transport does, now and then, and the worker dies of it)."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from queue import Empty

from kombu import Connection

from workers.fs_broker import SCHEME


def _race(scheme: str, folder: Path, count: int = 400) -> list[int]:
    """Messages put by one connection while another polls as fast as it can; what it got."""
    options = {"data_folder_in": str(folder), "data_folder_out": str(folder)}
    got: list[int] = []
    with Connection(f"{scheme}://localhost//", transport_options=options) as producer, \
            Connection(f"{scheme}://localhost//", transport_options=options) as consumer:
        sending, receiving = producer.default_channel, consumer.default_channel

        def produce() -> None:
            for n in range(count):
                sending._put("q", {"n": n, "padding": "x" * 50_000})

        thread = threading.Thread(target=produce)
        thread.start()
        deadline = time.monotonic() + 60
        while len(got) < count and time.monotonic() < deadline:
            try:
                got.append(receiving._get("q")["n"])
            except Empty:
                continue
        thread.join()
    return got


def test_every_message_arrives_whole(tmp_path: Path) -> None:
    assert sorted(_race(SCHEME, tmp_path)) == list(range(400))


def _bind(folder: str, queue: str, start_at: float) -> None:
    options = {"data_folder_in": folder, "data_folder_out": folder, "control_folder": folder}
    with Connection(f"{SCHEME}://localhost//", transport_options=options) as conn:
        channel = conn.default_channel
        while time.time() < start_at:  # all processes bind at once
            pass
        channel._queue_bind("celery", queue, "", queue)


def test_workers_binding_at_once_all_land_in_the_exchange_table(tmp_path: Path) -> None:
    """kombu's own bind creates a missing table before it locks it, so a worker starting
    beside another can read it empty and die of a JSON error at start-up."""
    from concurrent.futures import ProcessPoolExecutor
    from multiprocessing import get_context

    from workers.fs_broker import Channel

    queues = [f"q{n}" for n in range(6)]
    for round_ in range(3):
        folder = tmp_path / str(round_)
        folder.mkdir()
        start_at = time.time() + 2.0
        with ProcessPoolExecutor(len(queues), mp_context=get_context("spawn")) as pool:
            for done in [pool.submit(_bind, str(folder), q, start_at) for q in queues]:
                done.result()
        options = {"data_folder_in": str(folder), "data_folder_out": str(folder),
                   "control_folder": str(folder)}
        with Connection(f"{SCHEME}://localhost//", transport_options=options) as conn:
            channel = conn.default_channel
            assert isinstance(channel, Channel)
            assert sorted(q.queue for q in channel.get_table("celery")) == queues
