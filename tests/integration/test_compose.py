"""docker-compose.yml: passes `docker compose config` (or docker-compose v1's) and wires the
services docs/architecture.md names."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest
import yaml

from tests.integration.services import ROOT

COMPOSE = ROOT / "docker-compose.yml"


def _compose_command() -> list[str] | None:
    docker = shutil.which("docker")
    if docker and subprocess.run([docker, "compose", "version"], capture_output=True
                                 ).returncode == 0:
        return [docker, "compose"]
    legacy = shutil.which("docker-compose")
    return [legacy] if legacy else None


def test_compose_config_is_valid() -> None:
    command = _compose_command()
    if command is None:
        pytest.skip("neither the docker compose plugin nor docker-compose is installed")
    result = subprocess.run([*command, "-f", str(COMPOSE), "config", "-q"], cwd=ROOT,
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr


def _doc() -> dict[str, Any]:
    return dict(yaml.safe_load(Path(COMPOSE).read_text()))


def test_compose_runs_the_whole_service() -> None:
    services = _doc()["services"]
    assert {"redis", "postgres", "minio", "gateway", "worker-cpu", "worker-validate",
            "worker-gpu"} <= set(services)
    gpu = services["worker-gpu"]
    assert gpu["command"][-1] == "gpu"
    devices = gpu["deploy"]["resources"]["reservations"]["devices"]
    assert devices[0]["capabilities"] == ["gpu"]
    assert services["worker-cpu"]["command"][-1] == "cpu"
    assert "validate" in services["worker-validate"]["command"]
    env = services["gateway"]["environment"]
    assert env["VOLUMESH_BROKER_URL"].startswith("redis://redis")
    assert env["VOLUMESH_DATABASE_URL"].startswith("postgresql://")
    assert env["VOLUMESH_STORAGE_URL"].startswith("s3://")
    assert set(_doc()["volumes"]) >= {"redis-data", "postgres-data", "minio-data"}
