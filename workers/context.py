"""What a worker process holds open between tasks: settings, job store, storage, and the
enhance stage's networks."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

from workers.db import init_db, make_engine, make_sessionmaker
from workers.jobstore import JobStore
from workers.settings import Settings
from workers.storage import Storage, make_storage

if TYPE_CHECKING:
    from pipeline.enhance.config import EnhanceConfig
    from pipeline.enhance.networks import EnhanceNetworks

log = logging.getLogger(__name__)


@dataclass
class WorkerContext:
    """What a worker process holds open: settings, job store, storage, and the enhance
    stage's networks between jobs."""

    settings: Settings
    store: JobStore
    storage: Storage
    networks: EnhanceNetworks | None = None
    """The networks of the last enhance stage this process ran (`enhance_networks`)."""

    @classmethod
    def create(cls, settings: Settings) -> WorkerContext:
        engine = make_engine(settings)
        init_db(engine)
        return cls(settings, JobStore(make_sessionmaker(engine)), make_storage(settings))

    def enhance_networks(self, config: EnhanceConfig) -> EnhanceNetworks:
        """The networks `config` runs: those kept from the last enhance stage where they
        fit it, else loaded now and kept in their place (one set at a time, so a worker
        holds one LDM: the old set is let go before the new one loads)."""
        from pipeline.enhance.networks import load_networks

        if self.networks is None or not self.networks.fits(config):
            started = time.perf_counter()
            self.networks = None
            self.networks = load_networks(config)
            log.info("enhance networks for %s on %s loaded in %.2f s", config.method,
                     self.networks.key[1], time.perf_counter() - started)
        return self.networks
