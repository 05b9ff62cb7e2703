"""The gateway application: ``create_app(settings)``."""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI
from fastapi.middleware.cors import CORSMiddleware

from app.api.routes import assets, captures, health, jobs, live, rigs, streams
from app.core import problems
from app.core.capture_store import sweep_abandoned
from app.core.context import Gateway
from app.core.leases import sweep_leases
from app.core.limits import BodyLimitMiddleware
from app.core.live import PreviewHub
from app.core.live_redis import relay_for
from app.core.metrics import MetricsMiddleware
from app.core.retention import sweep_retention
from app.core.uploads import (
    BodyIdleTimeoutMiddleware,
    clean_stale_uploads,
    sweep_stale_uploads,
)
from app.docs import mount_docs
from app.schemas import API_PREFIX
from workers.settings import Settings, get_settings

log = logging.getLogger(__name__)

DESCRIPTION = """Multi-camera RGB-D captures in, Draco-compressed glTF meshes out.

Upload a capture zip (`POST /api/v1/captures`), queue a job (`POST /api/v1/jobs`), follow it
(`GET /api/v1/jobs/{id}` or its server-sent `events`) and fetch `mesh.glb` from its asset.
Writes need `Authorization: Bearer <api key>`; errors are RFC 9457 problem+json."""


def _include_api(app: FastAPI) -> None:
    # Each resource router straight on the app (not nested in an /api/v1 router): one routing
    # level less on every request.
    for module in (captures, jobs, assets, rigs, streams, live):
        app.include_router(module.router, prefix=API_PREFIX)


def _mount_viewer(app: FastAPI) -> None:
    try:
        from app.web import mount_viewer
    except ImportError:
        return
    try:
        mount_viewer(app)
    except ValueError as exc:  # no static/ in this install: the API alone
        log.info("viewer not served: %s", exc)


def create_app(settings: Settings | None = None, *, viewer: bool = True) -> FastAPI:
    """The gateway for ``settings`` (default: from ``VOLUMESH_*``)."""
    settings = settings or get_settings()
    gateway = Gateway.create(settings)
    previews = PreviewHub()

    @asynccontextmanager
    async def lifespan(_: FastAPI) -> AsyncIterator[None]:
        gateway.start()
        relay = app.state.preview_relay = relay_for(settings.broker_url, previews)
        removed = clean_stale_uploads(settings.tmp_dir, settings.stale_upload_s)
        if removed:
            log.info("removed %d partial uploads left by a stopped gateway", removed)
        sweepers = [asyncio.create_task(sweep_stale_uploads(settings.tmp_dir,
                                                            settings.stale_upload_s)),
                    asyncio.create_task(sweep_leases(gateway)),
                    asyncio.create_task(sweep_retention(gateway)),
                    asyncio.create_task(sweep_abandoned(gateway))]
        yield
        for sweeper in sweepers:
            sweeper.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await sweeper
        if relay is not None:
            relay.close()
        gateway.close()

    app = FastAPI(title="volumesh", version="0.1.0", description=DESCRIPTION,
                  lifespan=lifespan, docs_url=None, openapi_url="/openapi.json")
    app.state.gateway = gateway
    app.state.previews = previews  # live previews: this process's viewers
    app.state.preview_relay = None  # set on start with a Redis broker (app.core.live_redis)
    problems.install(app)
    _include_api(app)
    app.include_router(health.router)
    mount_docs(app)
    if viewer:
        _mount_viewer(app)
    app.add_middleware(BodyIdleTimeoutMiddleware, idle_timeout_s=settings.upload_idle_timeout_s)
    app.add_middleware(BodyLimitMiddleware, upload_limit=settings.max_upload_bytes,
                       json_limit=settings.max_json_bytes,
                       frame_set_limit=settings.max_frame_set_bytes)
    if settings.cors_origins:
        app.add_middleware(CORSMiddleware, allow_origins=settings.cors_origins,
                           allow_methods=["GET", "HEAD", "POST", "PUT", "DELETE", "OPTIONS"],
                           allow_headers=["Authorization", "Content-Type", "Range",
                                          "If-None-Match", "If-Range", "Volumesh-Timestamp-Us"],
                           expose_headers=["ETag", "Content-Range", "Accept-Ranges", "Location",
                                           "Content-Length"])
    app.add_middleware(MetricsMiddleware, metrics=gateway.metrics)
    return app


def app_from_env() -> FastAPI:
    """Factory for ``uvicorn --factory app.main:app_from_env`` (settings from the environment)."""
    return create_app()
