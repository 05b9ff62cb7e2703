"""Fixtures of the workers' tests: a real S3-compatible server (moto) with one bucket."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.integration.services import MotoS3

BUCKET = "volumesh-test"


@pytest.fixture(scope="module")
def moto(tmp_path_factory: pytest.TempPathFactory) -> Iterator[MotoS3]:
    server = MotoS3(tmp_path_factory.mktemp("moto")).start()
    server.make_bucket(BUCKET)
    yield server
    server.stop()
