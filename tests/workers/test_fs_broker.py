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
