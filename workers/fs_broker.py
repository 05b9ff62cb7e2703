"""The embedded broker: kombu's file-system transport with atomic message writes.

kombu creates a message file and then writes it, and its reader takes any file with the
queue's suffix without a lock; a worker polling in between reads an empty message, fails to
decode it and stops with "Unrecoverable error". Here a message is written under a name no
reader picks up and renamed into place, so a reader sees it whole or not at all.
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


class Transport(filesystem.Transport):
    Channel = Channel
    driver_type = driver_name = SCHEME


TRANSPORT_ALIASES[SCHEME] = f"{__name__}:Transport"
