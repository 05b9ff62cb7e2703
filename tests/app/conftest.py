"""A gateway in-process (TestClient) with a real embedded-broker worker process beside it."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from app.core.security import create_key
from app.main import create_app
from tests.integration.services import Process, base_env, make_capture_zip, wait_worker_ready
from tests.integration.services import worker as worker_process
from workers.settings import MiB, Settings

LIMITS = {"max_upload_bytes": str(8 * MiB), "max_unpacked_bytes": str(6 * MiB),
          "max_capture_files": "200", "max_json_bytes": str(16 * 1024),
          "validation_timeout_s": "60"}


@dataclass
class Service:
    client: TestClient
    settings: Settings
    key: str
    worker: Process
    capture_zip: Path
    data_dir: Path

    @property
    def auth(self) -> dict[str, str]:
        """The Authorization header ``client`` sends unless told otherwise."""
        return {"Authorization": f"Bearer {self.key}"}


@pytest.fixture(scope="session")
def small_capture_zip(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_capture_zip(tmp_path_factory.mktemp("captures"), cameras=2, width=64, height=48)


@pytest.fixture(scope="session")
def service(tmp_path_factory: pytest.TempPathFactory, small_capture_zip: Path
            ) -> Iterator[Service]:
    data_dir = tmp_path_factory.mktemp("volumesh-data")
    values = {"data_dir": str(data_dir), **LIMITS}
    env = base_env(**values)
    settings = Settings.model_validate(values)
    worker = worker_process(env, data_dir / "worker.log", queues="validate").start()
    app = create_app(settings, viewer=False)
    with TestClient(app, raise_server_exceptions=False) as client:
        with app.state.gateway.sessions() as session:
            _, key = create_key(session, "tests")
        client.headers["Authorization"] = f"Bearer {key}"  # requests with none: ANONYMOUS
        wait_worker_ready(worker)
        yield Service(client, settings, key, worker, small_capture_zip, data_dir)
    worker.stop()


def admin_auth(service: Service) -> dict[str, str]:
    """The Authorization header of a new admin key of the service."""
    gateway = service.client.app.state.gateway  # type: ignore[attr-defined]
    with gateway.sessions() as session:
        _, key = create_key(session, "admin", admin=True)
    return {"Authorization": f"Bearer {key}"}
