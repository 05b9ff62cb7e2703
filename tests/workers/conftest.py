"""Fixtures of the workers' tests: a real S3-compatible server (moto) with one bucket, and the
settings of a job store on SQLite and on a fresh PostgreSQL database."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.integration.services import MotoS3, fresh_postgres_db, postgres_available
from workers.settings import Settings

BUCKET = "volumesh-test"


@pytest.fixture(scope="session")
def moto(tmp_path_factory: pytest.TempPathFactory) -> Iterator[MotoS3]:
    """One server for the session (its bucket is shared as by the tests of a module: each
    test writes keys of its own)."""
    server = MotoS3(tmp_path_factory.mktemp("moto")).start()
    server.make_bucket(BUCKET)
    yield server
    server.stop()


@pytest.fixture(params=["sqlite", "postgresql"])
def store_settings(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Settings]:
    """Settings whose job store is a SQLite file, then a fresh PostgreSQL database (skipped
    where none runs)."""
    if request.param == "sqlite":
        yield Settings(data_dir=tmp_path)
        return
    if not postgres_available():
        pytest.skip("no PostgreSQL on 127.0.0.1:5432")
    with fresh_postgres_db() as url:
        yield Settings(data_dir=tmp_path, database_url=url)
