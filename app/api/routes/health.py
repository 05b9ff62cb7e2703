"""GET /healthz (the process answers), /readyz (broker, job store and storage reachable, a live
worker on every queue), /metrics (for its token or an admin key)."""

from __future__ import annotations

import hmac

from fastapi import APIRouter
from fastapi.responses import JSONResponse, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from sqlalchemy import text

from app.api.deps import BearerDep, GatewayDep, authenticate
from app.core.context import Gateway
from app.core.problems import SERVER_ERROR, ProblemError, problem_responses
from app.schemas import Health
from workers.celery_app import QUEUES

router = APIRouter(tags=["health"])
_METRICS_PROBLEMS = {401: "No valid token or API key (`unauthorized`, "
                          "`WWW-Authenticate: Bearer`).",
                     403: "An API key that is not an admin key (`forbidden`)."}


@router.get("/healthz", response_model=Health, responses=problem_responses(SERVER_ERROR))
def healthz() -> Health:
    return Health(status="ok")


def _check(gateway: Gateway) -> dict[str, str]:
    checks: dict[str, str] = {}
    try:
        with gateway.engine.connect() as conn:
            conn.execute(text("SELECT 1"))
        checks["database"] = "ok"
    except Exception as exc:
        checks["database"] = f"unreachable: {type(exc).__name__}"
    try:
        gateway.storage.ping()
        checks["storage"] = "ok"
    except Exception as exc:
        checks["storage"] = f"unreachable: {type(exc).__name__}"
    try:
        gateway.ping_broker()
        checks["broker"] = "ok"
    except Exception as exc:
        checks["broker"] = f"unreachable: {type(exc).__name__}"
    try:
        consumed = gateway.queues.get()
        idle = [queue for queue in QUEUES if queue not in consumed]
        checks["queues"] = f"no live worker consumes {', '.join(idle)}" if idle else "ok"
    except Exception as exc:
        checks["queues"] = f"unknown: {type(exc).__name__}"
    return checks


# A 503 here is the readiness report itself (Health, application/json), not a problem: probes
# and people read its `checks`.
@router.get("/readyz", response_model=Health, responses={
    503: {"model": Health, "description": "Something it depends on is unreachable, or a queue "
                                          "(`cpu`, `gpu`, `validate`) has no live worker."},
    **problem_responses(SERVER_ERROR)})
def readyz(gateway: GatewayDep) -> Response:
    checks = _check(gateway)
    ok = all(v == "ok" for v in checks.values())
    body = Health(status="ok" if ok else "unavailable", checks=checks)
    return JSONResponse(body.model_dump(), status_code=200 if ok else 503)


@router.get("/metrics", response_class=Response,
            responses={200: {"content": {CONTENT_TYPE_LATEST: {"schema": {"type": "string"}}}},
                       **problem_responses(_METRICS_PROBLEMS, SERVER_ERROR)})
def metrics(gateway: GatewayDep, credentials: BearerDep) -> Response:
    """Prometheus metrics, for `VOLUMESH_METRICS_TOKEN` or an admin API key."""
    token = gateway.settings.metrics_token
    sent = None if credentials is None else credentials.credentials
    if token is None or sent is None or not hmac.compare_digest(
            sent.encode(), token.get_secret_value().encode()):
        caller = authenticate(gateway, credentials)
        if not caller.admin:
            raise ProblemError(403, "Metrics are read with VOLUMESH_METRICS_TOKEN or an admin "
                               "key (`volumesh keys create --admin`).", kind="forbidden")
    registry = gateway.metrics.registry
    return Response(generate_latest(registry), media_type=CONTENT_TYPE_LATEST)
