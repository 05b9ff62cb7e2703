"""``/docs``: the OpenAPI explorer, served offline from ``node_modules/swagger-ui-dist``.

FastAPI's default page loads Swagger UI from a CDN, which leaves it blank on a machine with no
network; the npm set-up vendors the same files and the gateway serves them itself.
"""

from __future__ import annotations

import logging
from pathlib import Path

from fastapi import FastAPI
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import HTMLResponse
from starlette.staticfiles import StaticFiles

log = logging.getLogger(__name__)

SWAGGER_DIR = Path(__file__).resolve().parents[1] / "node_modules" / "swagger-ui-dist"
_PREFIX = "/vendor/swagger-ui"


def mount_docs(app: FastAPI, *, swagger_dir: Path = SWAGGER_DIR) -> None:
    """Serves ``/docs`` with Swagger UI from ``swagger_dir``, files under ``/vendor/swagger-ui``."""
    if not (swagger_dir / "swagger-ui-bundle.js").is_file():
        log.warning("swagger-ui-dist is missing at %s: /docs needs `npm ci`", swagger_dir)
        return
    app.mount(_PREFIX, StaticFiles(directory=swagger_dir), name="swagger-ui")

    @app.get("/docs", include_in_schema=False)
    async def docs_page() -> HTMLResponse:
        return get_swagger_ui_html(
            openapi_url=app.openapi_url or "/openapi.json",
            title=f"{app.title} API",
            swagger_js_url=f"{_PREFIX}/swagger-ui-bundle.js",
            swagger_css_url=f"{_PREFIX}/swagger-ui.css",
            swagger_favicon_url=f"{_PREFIX}/favicon-32x32.png",
        )
