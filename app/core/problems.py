"""Errors as RFC 9457 problem details (``application/problem+json``).

Every error the gateway returns goes through here, validation errors included, so a client
always gets ``{"type", "title", "status", "detail"}`` with a ``detail`` a person can act on.
"""

from __future__ import annotations

import logging
from http import HTTPStatus
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from app.schemas import Problem

PROBLEM_MEDIA_TYPE = "application/problem+json"
PROBLEM_TYPE_BASE = "https://volumesh.dev/problems/"

log = logging.getLogger(__name__)

# The statuses shared by routes, for ``problem_responses``: each route adds its own (404, ...).
SERVER_ERROR = {500: "A bug in the gateway, logged whole; bad input never gives one."}
UNAVAILABLE = {503: "The job store or the broker is unreachable (`service-unavailable`, "
                    "`Retry-After: 5`); nothing was changed."}
READ = {401: "No valid API key (`unauthorized`, `WWW-Authenticate: Bearer`).",
        422: "A path or query parameter of the wrong form (`validation-error`).",
        **UNAVAILABLE, **SERVER_ERROR}
WRITE = {401: "No valid API key (`unauthorized`, `WWW-Authenticate: Bearer`).",
         422: "A bad body or parameter (`validation-error`, with `errors`).",
         **UNAVAILABLE, **SERVER_ERROR}
BODY = {400: "The body cannot be read as JSON: not UTF-8 text (`malformed-body`).",
        408: "The body stopped arriving for `VOLUMESH_UPLOAD_IDLE_TIMEOUT_S` (`body-timeout`).",
        413: "The body is over `VOLUMESH_MAX_JSON_BYTES` (`body-too-large`)."}
# What FastAPI says of a body it cannot decode at all (JSON that fails to parse is a 422).
_UNREADABLE_BODY = "There was an error parsing the body"
# Headers every problem of a status carries (the 401 challenge, when to retry a 503).
_HEADERS = {401: ("WWW-Authenticate", "`Bearer realm=\"volumesh\"`."),
            503: ("Retry-After", "Seconds to wait before trying again.")}


def located(status: int, description: str) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses=`` entry of a success that names what it made in ``Location``."""
    return {status: {"description": description, "headers": {"Location": {
        "description": "The URL of what was made.", "required": True,
        "schema": {"type": "string"}}}}}


def problem_responses(*statuses: dict[int, str]) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses=`` declaring each status (later dicts win) with a problem+json body."""
    merged: dict[int, str] = {}
    for more in statuses:
        merged.update(more)
    schema = Problem.model_json_schema()
    declared: dict[int | str, dict[str, Any]] = {}
    for status, text in sorted(merged.items()):
        declared[status] = {"description": text,
                            "content": {PROBLEM_MEDIA_TYPE: {"schema": schema}}}
        if status in _HEADERS:
            name, description = _HEADERS[status]
            declared[status]["headers"] = {name: {"description": description, "required": True,
                                                  "schema": {"type": "string"}}}
    return declared


class ProblemError(Exception):
    """Raised anywhere in the gateway to answer with a problem."""

    def __init__(self, status: int, detail: str, *, kind: str | None = None,
                 headers: dict[str, str] | None = None, **extra: Any) -> None:
        super().__init__(detail)
        self.status = status
        self.detail = detail
        self.kind = kind
        self.headers = headers or {}
        self.extra = extra


def problem_response(status: int, detail: str, *, kind: str | None = None,
                     instance: str | None = None, headers: dict[str, str] | None = None,
                     **extra: Any) -> JSONResponse:
    title = HTTPStatus(status).phrase if status in HTTPStatus._value2member_map_ else "Error"
    slug = kind or title.lower().replace(" ", "-")
    body: dict[str, Any] = {"type": PROBLEM_TYPE_BASE + slug, "title": title,
                            "status": status, "detail": detail}
    if instance:
        body["instance"] = instance
    body.update(extra)
    return JSONResponse(body, status_code=status, headers=headers,
                        media_type=PROBLEM_MEDIA_TYPE)


def _location(loc: tuple[Any, ...] | list[Any]) -> str:
    parts = [str(p) for p in loc if p not in ("body",)] or ["body"]
    return ".".join(parts)


def _validation_detail(errors: list[dict[str, Any]]) -> str:
    messages = []
    for error in errors[:5]:
        where = _location(error.get("loc", ()))
        messages.append(f"{where}: {error.get('msg', 'invalid')}")
    more = f" (and {len(errors) - 5} more)" if len(errors) > 5 else ""
    return "; ".join(messages) + more


async def _on_problem(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, ProblemError)
    return problem_response(exc.status, exc.detail, kind=exc.kind, instance=request.url.path,
                            headers=exc.headers, **exc.extra)


async def _on_http(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, StarletteHTTPException)
    status = exc.status_code
    detail = exc.detail if isinstance(exc.detail, str) else str(exc.detail)
    kind = None
    if status == 404 and detail == "Not Found":
        detail = f"There is no resource at {request.url.path}; the API lives under /api/v1."
    elif status == 405:
        detail = f"{request.method} is not allowed on {request.url.path}."
    elif status == 400 and detail == _UNREADABLE_BODY:
        detail, kind = ("The body cannot be read as JSON: send UTF-8 JSON with "
                        "'Content-Type: application/json'."), "malformed-body"
    return problem_response(status, detail, kind=kind, instance=request.url.path,
                            headers=dict(exc.headers or {}))


async def _on_validation(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, RequestValidationError)
    errors = [dict(e) for e in exc.errors()]
    public = [{"loc": list(e.get("loc", ())), "msg": e.get("msg"), "type": e.get("type")}
              for e in errors]
    return problem_response(422, _validation_detail(errors), kind="validation-error",
                            instance=request.url.path, errors=public)


async def _on_unavailable(request: Request, exc: Exception) -> JSONResponse:
    # The broker or the job store is down: nothing the client did; worth retrying.
    from kombu.exceptions import OperationalError as BrokerError

    what = "task broker" if isinstance(exc, BrokerError) else "job store"
    log.warning("%s unreachable on %s %s: %s", what, request.method, request.url.path, exc)
    return problem_response(503, f"The {what} is unreachable; nothing was queued or changed. "
                            "Try again shortly.", kind="service-unavailable",
                            instance=request.url.path, headers={"Retry-After": "5"})


async def _on_unexpected(request: Request, exc: Exception) -> JSONResponse:
    # A bug, not bad input: log it whole, tell the client without leaking internals.
    log.exception("unhandled error on %s %s", request.method, request.url.path)
    return problem_response(500, "The server failed unexpectedly; the error was logged.",
                            instance=request.url.path)


def install(app: FastAPI) -> None:
    """Route every error of ``app`` through problem+json."""
    app.add_exception_handler(ProblemError, _on_problem)
    app.add_exception_handler(StarletteHTTPException, _on_http)
    app.add_exception_handler(RequestValidationError, _on_validation)
    from kombu.exceptions import OperationalError as BrokerError
    from sqlalchemy.exc import InterfaceError, OperationalError

    for unavailable in (BrokerError, OperationalError, InterfaceError):
        app.add_exception_handler(unavailable, _on_unavailable)
    app.add_exception_handler(Exception, _on_unexpected)
