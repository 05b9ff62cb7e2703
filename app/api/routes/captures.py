"""POST /captures (upload), GET /captures, GET /captures/{id}.

An upload is streamed to disk and hashed, checked at zip level here, stored (once per content),
then read whole by a worker (``volumesh.validate_capture`` on the ``validate`` queue) while the
request waits: the client learns in the same response whether the capture is usable. A
rejected capture is deleted again, so nothing half-valid is ever kept.
"""

from __future__ import annotations

import asyncio
import time
from typing import Annotated, Any

from fastapi import APIRouter, Path, Request, Response
from sqlalchemy import select
from starlette.concurrency import run_in_threadpool

from app.api.deps import CallerDep, GatewayDep, SessionDep
from app.api.pagination import PageLimit, PageOffset, fetch_page
from app.core.capture_store import forget
from app.core.context import Gateway
from app.core.problems import BODY, READ, WRITE, ProblemError, located, problem_responses
from app.core.security import can_use_capture
from app.core.uploads import ReceivedUpload, receive_upload
from app.core.zipcheck import ZipLimits, check_zip
from app.schemas import API_PREFIX, ID_PATTERN, CapturePage, CapturePublic
from workers.capture_registry import CaptureZip, Registered, register_capture
from workers.celery_app import QUEUE_VALIDATE, TASK_VALIDATE
from workers.models import Capture, CaptureGrant

router = APIRouter(prefix="/captures", tags=["captures"])

_POLL_S = 0.05
_UPLOAD_BODY: dict[str, Any] = {
    "requestBody": {
        "required": True,
        "description": "A capture zip in format v1 (docs/capture-format.md): the raw body, or a "
                       "multipart form with the zip in the field `file`.",
        "content": {
            "application/zip": {"schema": {"type": "string", "format": "binary"}},
            "multipart/form-data": {"schema": {
                "type": "object", "required": ["file"],
                "properties": {"file": {"type": "string", "format": "binary"}}}},
        },
    },
}


_UPLOAD_PROBLEMS = {
    400: "Not a zip or a damaged one (`not-a-zip`), an empty body (`empty-upload`), a malformed "
         "form or one without (or with two) `file` fields, a bad `Content-Length`, the client "
         "gone mid-upload (`upload-interrupted`).",
    409: "The capture was removed while it was being validated.",
    413: "Over `VOLUMESH_MAX_UPLOAD_BYTES` (`upload-too-large`, `body-too-large`), too many "
         "entries (`too-many-files`), too large unpacked or too compressed (`zip-bomb`).",
    415: "Another Content-Type (`unsupported-media-type`).",
    422: "Refused at zip level (`invalid-capture-zip`) or by the reader (`invalid-capture`), "
         "the detail naming the file and field.",
    503: "No worker validated it within `VOLUMESH_VALIDATION_TIMEOUT_S` (`validation-timeout`, "
         "`Retry-After: 30`), the gateway stopped mid-upload, or the job store or broker is "
         "unreachable; the capture is not kept.",
}


def _limits(gateway: Gateway) -> ZipLimits:
    s = gateway.settings
    return ZipLimits(max_files=s.max_capture_files, max_unpacked_bytes=s.max_unpacked_bytes,
                     max_compression_ratio=s.max_compression_ratio)


def _register(gateway: Gateway, upload: ReceivedUpload, owner: str) -> Registered:
    zipped = CaptureZip(upload.path, upload.sha256, upload.size_bytes)
    return register_capture(gateway.sessions, gateway.storage, zipped, owner,
                            gateway.settings.validation_timeout_s)


def _state(gateway: Gateway, capture_id: str) -> Capture | None:
    with gateway.sessions() as session:
        return session.get(Capture, capture_id)


async def _settled(gateway: Gateway, capture_id: str, row: Capture | None) -> Capture:
    """The answer for a capture whose validation has ended: the row, or the problem."""
    if row is None:
        raise ProblemError(409, "The capture was removed while it was being validated; "
                           "upload it again.")
    if row.state == "rejected":
        await run_in_threadpool(forget, gateway, capture_id)
        raise ProblemError(422, f"The capture is not valid: {row.error}",
                           kind="invalid-capture")
    return row


async def _await_validation(gateway: Gateway, capture_id: str) -> Capture:
    timeout_s = gateway.settings.validation_timeout_s
    deadline = time.monotonic() + timeout_s
    while time.monotonic() <= deadline:
        row = await run_in_threadpool(_state, gateway, capture_id)
        if row is None or row.state != "validating":
            return await _settled(gateway, capture_id, row)
        await asyncio.sleep(_POLL_S)
    # Out of time: end the validation here, so the capture is not left `validating` for good
    # (a worker that died on it, or none running); one that finished meanwhile is kept.
    if not await run_in_threadpool(forget, gateway, capture_id, "validating"):
        return await _settled(gateway, capture_id,
                              await run_in_threadpool(_state, gateway, capture_id))
    raise ProblemError(
        503, f"No worker finished validating the capture within {timeout_s:.0f} s: none is "
        f"running on the '{QUEUE_VALIDATE}' queue, or the one reading it died. The capture "
        "was not kept; upload it again later.",
        kind="validation-timeout", headers={"Retry-After": "30"})


@router.post("", status_code=201, response_model=CapturePublic, openapi_extra=_UPLOAD_BODY,
             summary="Upload a capture zip",
             responses={**located(201, "The capture, read whole and ready."),
                        **problem_responses(WRITE, BODY, _UPLOAD_PROBLEMS)})
async def upload_capture(request: Request, response: Response, gateway: GatewayDep,
                         caller: CallerDep) -> CapturePublic:
    """Stores the capture (once per content) after a worker has read it whole; it belongs to
    the key's owner.

    Uploading identical bytes again returns the same capture (201, with the header
    `Volumesh-Deduplicated: true` when the key's owner had uploaded them before).
    """
    settings = gateway.settings
    upload = await receive_upload(request, settings.tmp_dir, settings.max_upload_bytes)
    try:
        await run_in_threadpool(check_zip, upload.path, _limits(gateway))
        registered = await run_in_threadpool(_register, gateway, upload, caller.owner)
    finally:
        upload.path.unlink(missing_ok=True)
    capture_id = registered.capture_id
    if registered.needs_validation:
        try:
            await run_in_threadpool(gateway.send_task, TASK_VALIDATE, [capture_id],
                                    QUEUE_VALIDATE)
        except Exception:
            # Not queued, so never validated: do not keep it half-accepted.
            await run_in_threadpool(forget, gateway, capture_id, "validating")
            raise
    if registered.had_it:
        response.headers["Volumesh-Deduplicated"] = "true"
    row = await _await_validation(gateway, capture_id)
    response.headers["Location"] = f"{API_PREFIX}/captures/{row.id}"
    return CapturePublic.of(row)


CaptureId = Annotated[str, Path(pattern=ID_PATTERN, description="A capture id.")]


@router.get("/{capture_id}", response_model=CapturePublic,
            responses=problem_responses(READ, {404: "There is no such capture (or another "
                                               "owner's)."}))
def get_capture(capture_id: CaptureId, session: SessionDep, caller: CallerDep) -> CapturePublic:
    row = session.get(Capture, capture_id)
    if row is None or row.state == "rejected" or not can_use_capture(session, caller, row.id):
        raise ProblemError(404, f"There is no capture {capture_id}.", kind="not-found")
    return CapturePublic.of(row)


@router.get("", response_model=CapturePage, responses=problem_responses(READ))
def list_captures(session: SessionDep, caller: CallerDep, limit: PageLimit = 20,
                  offset: PageOffset = 0) -> CapturePage:
    query = select(Capture).where(Capture.state == "ready")
    if not caller.admin:
        query = query.where(Capture.id.in_(
            select(CaptureGrant.capture_id).where(CaptureGrant.owner == caller.owner)))
    rows, total = fetch_page(session, query, (Capture.created_at.desc(), Capture.id), limit,
                             offset)
    return CapturePage(items=[CapturePublic.of(r) for r in rows], total=total, limit=limit,
                       offset=offset)
