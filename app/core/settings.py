"""The service settings (``VOLUMESH_*``).

Defined in :mod:`workers.settings` because workers read them too and must not import ``app``
(layers point one way: app -> workers -> pipeline); re-exported here for the gateway.
"""

from workers.settings import GiB, MiB, Settings, get_settings

__all__ = ["GiB", "MiB", "Settings", "get_settings"]
