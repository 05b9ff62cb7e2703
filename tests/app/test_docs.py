"""app.docs: /docs works offline, its Swagger UI files served by the gateway itself."""

from __future__ import annotations

import re

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from app.docs import SWAGGER_DIR, mount_docs


@pytest.fixture(scope="module")
def client() -> TestClient:
    if not (SWAGGER_DIR / "swagger-ui-bundle.js").is_file():
        pytest.fail(f"swagger-ui-dist is missing at {SWAGGER_DIR}: run `npm ci`", pytrace=False)
    app = FastAPI(docs_url=None)
    mount_docs(app)
    return TestClient(app)


def test_docs_page_loads_nothing_from_outside(client: TestClient) -> None:
    page = client.get("/docs")
    assert page.status_code == 200
    assert "https://" not in page.text and "http://" not in page.text
    urls = re.findall(r"""(?:src|href)=["']([^"']+)["']""", page.text)
    assert any(u.endswith("swagger-ui-bundle.js") for u in urls)
    for url in urls:
        assert client.get(url).status_code == 200, url


def test_docs_without_the_npm_files_is_simply_absent(tmp_path: object) -> None:
    app = FastAPI(docs_url=None)
    mount_docs(app, swagger_dir=SWAGGER_DIR / "missing")
    assert TestClient(app).get("/docs").status_code == 404
