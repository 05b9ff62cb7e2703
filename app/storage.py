"""Storage of captures and assets, defined in :mod:`workers.storage` (workers use it too and
must not import ``app``); re-exported for the gateway."""

from workers.storage import LocalStorage, S3Storage, Storage, make_storage

__all__ = ["LocalStorage", "S3Storage", "Storage", "make_storage"]
