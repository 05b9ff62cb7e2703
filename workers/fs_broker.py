"""The embedded broker: kombu's file-system transport with atomic message writes.

kombu creates a message file and then writes it, and its reader takes any file with the
queue's suffix without a lock; a worker polling in between reads an empty message, fails to
decode it and stops with "Unrecoverable error". Here a message is written under a name no
reader picks up and renamed into place, so a reader sees it whole or not at all.

Binding a queue has the same race: kombu creates a missing exchange table and only then locks
and writes it, so a second worker starting at the same moment can lock it first, read it
empty and die of the JSON error. Here binds take a lock of their own for the whole
read-modify-write, and the table is replaced whole.
"""

from __future__ import annotations

import os
import time
import uuid
from typing import Any

from kombu.exceptions import ChannelError
from kombu.transport import TRANSPORT_ALIASES, filesystem
from kombu.utils.encoding import str_to_bytes
from kombu.utils.json import dumps

SCHEME = "volumeshfs"
"""Broker URL scheme of this transport (``volumeshfs://localhost//``)."""


class Channel(filesystem.Channel):
    # kombu's base and file-system channels disagree on this signature; this is the latter's.
    def _put(self, queue: Any, payload: Any, **kwargs: Any) -> None:  # type: ignore[override]
        # The same name as kombu's (time first, so readers take messages in order); the
        # temporary one starts with a dot, which never matches "<queue>.msg".
        name = f"{int(round(time.monotonic() * 1000))}_{uuid.uuid4()}.{queue}.msg"
        final = os.path.join(self.data_folder_out, name)
        partial = os.path.join(self.data_folder_out, f".{uuid.uuid4().hex}.partial")
        try:
            with open(partial, "wb") as out:
                out.write(str_to_bytes(dumps(payload)))
            os.replace(partial, final)
        except OSError as exc:
            raise ChannelError(f"Cannot add file {final!r} to directory") from exc


    def _queue_bind(self, exchange: str, routing_key: str, pattern: str, queue: str) -> None:
        table = self._exchange_file(exchange)
        self.control_folder.mkdir(exist_ok=True)
        entry = filesystem.exchange_queue_t(routing_key or "", pattern or "", queue or "")
        # The guard's name starts with a dot and does not end in ".exchange": no table.
        with open(self.control_folder / f".{exchange}.bind-lock", "a") as guard:
            filesystem.lock(guard, filesystem.LOCK_EX)
            try:
                queues = self.get_table(exchange)
                if entry in queues:
                    return
                partial = self.control_folder / f".{uuid.uuid4().hex}.partial"
                partial.write_bytes(str_to_bytes(dumps([entry, *queues])))
                os.replace(partial, table)
            finally:
                filesystem.unlock(guard)


class Transport(filesystem.Transport):
    Channel = Channel
    driver_type = driver_name = SCHEME


TRANSPORT_ALIASES[SCHEME] = f"{__name__}:Transport"
