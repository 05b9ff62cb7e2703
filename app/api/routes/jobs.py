"""POST /jobs, GET /jobs, GET /jobs/{id}, DELETE /jobs/{id}, GET /jobs/{id}/events.

A job with ``frames`` is a sequence: one frame job per capture frame, run in parallel
(`workers.sequence`); cancelling the sequence cancels its frames."""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Path, Query, Request, Response
from fastapi.responses import StreamingResponse
from sqlalchemy import bindparam, delete, select, update
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool

from app.api.deps import BearerDep, CallerDep, GatewayDep, SessionDep, authenticate
from app.api.pagination import PageLimit, PageOffset, fetch_page
from app.core.context import Gateway
from app.core.problems import BODY, READ, WRITE, ProblemError, located, problem_responses
from app.core.security import Caller, can_use_capture
from app.schemas import (
    API_PREFIX,
    ID_PATTERN,
    FrameRange,
    JobCreate,
    JobPage,
    JobPublic,
    JobState,
)
from workers.celery_app import QUEUE_CPU, TASK_STAGE
from workers.models import TERMINAL_STATES, Capture, Job, Rig, new_id, utcnow
from workers.sequence import SEQUENCE_STAGES, frame_over

router = APIRouter(prefix="/jobs", tags=["jobs"])

JobId = Annotated[str, Path(pattern=ID_PATTERN, description="A job id.")]
EVENT_POLL_S = 0.25
EVENT_KEEPALIVE_S = 15.0
_NO_JOB = {404: "There is no such job (or another owner's)."}
# OpenAPI 3.1 reads a text/event-stream schema as one event's: `event: job`, an `id:`, and
# `data:` holding the job as GET /jobs/{job_id} answers it (keep-alive comments are no events).
_EVENT_STREAM = {
    "type": "object",
    "required": ["event", "data"],
    "properties": {
        "event": {"const": "job"},
        "id": {"type": "string", "description": "The job's updated_at, as a Unix time."},
        "data": {"type": "string", "contentMediaType": "application/json",
                 "contentSchema": {"$ref": "#/components/schemas/JobPublic"}},
    },
}


def _not_found(job_id: str) -> ProblemError:
    return ProblemError(404, f"There is no job {job_id}.", kind="not-found")


def _ready_capture(session: Session, caller: Caller, capture_id: str) -> Capture:
    capture = session.get(Capture, capture_id)
    if (capture is None or capture.state == "rejected"
            or not can_use_capture(session, caller, capture_id)):
        raise ProblemError(404, f"There is no capture {capture_id}; upload it with "
                           "POST /api/v1/captures first.", kind="not-found")
    if capture.state != "ready":
        raise ProblemError(409, f"Capture {capture_id} is still being validated; "
                           "retry when its upload has returned.", kind="capture-not-ready")
    return capture


def _options(session: Session, caller: Caller, body: JobCreate) -> dict[str, Any]:
    """The job's options; a saved rig's poses are copied in, so the job stands on its own."""
    options = body.options()
    if body.rig_id is not None:
        rig = session.get(Rig, body.rig_id)
        if rig is None or not caller.sees(rig.owner):
            raise ProblemError(404, f"There is no rig {body.rig_id}; upload one with POST "
                               "/api/v1/rigs first.", kind="not-found")
        options["world_from_depth"] = rig.document["world_from_depth"]
    return options


def _create(gateway: Gateway, caller: Caller, body: JobCreate) -> Job:
    if body.frames is not None:
        return _create_sequence(gateway, caller, body)
    with gateway.sessions() as session:
        if body.calibration_capture_id is not None:
            _ready_capture(session, caller, body.calibration_capture_id)
        capture_id = body.capture_id or body.calibration_capture_id
        assert capture_id is not None  # JobCreate requires one of them
        capture = _ready_capture(session, caller, capture_id)
        job = Job(id=new_id(), capture_id=capture.id, owner=caller.owner,
                  options=_options(session, caller, body), stages=[], stage_timings={})
        session.add(job)
        session.commit()
    try:
        task_id = gateway.send_task(TASK_STAGE, [job.id, 0], QUEUE_CPU)
    except Exception:
        _forget_job(gateway, job.id)  # never queued: leave no job that would wait forever
        raise
    with gateway.sessions() as session:
        row = session.get(Job, job.id)
        assert row is not None
        if row.task_id is None:  # the worker may already have recorded itself
            row.task_id = task_id
            session.commit()
        return row


def _forget_job(gateway: Gateway, job_id: str) -> None:
    with gateway.sessions() as session:
        session.execute(delete(Job).where(Job.parent_id == job_id))
        row = session.get(Job, job_id)
        if row is not None:
            session.delete(row)
        session.commit()


def sequence_frames(capture: Capture, frames: Literal["all"] | FrameRange) -> list[int]:
    """The capture's frame indices a sequence job reconstructs; a 422 naming a range that
    reaches outside them."""
    indices = sorted(capture.frame_indices or range(capture.frames or 0))
    if not indices:
        raise ProblemError(422, f"Capture {capture.id} lists no frames.",
                           kind="validation-error")
    if frames == "all":
        return indices
    missing = [i for i in (frames.first, frames.last) if i not in indices]
    if missing:
        raise ProblemError(422, f"frames: the range {frames.first}..{frames.last} lies outside "
                           f"capture {capture.id}'s frames ({_span(indices)}); frame "
                           f"{missing[0]} is not one of them.", kind="validation-error")
    return [i for i in indices if frames.first <= i <= frames.last]


def _span(indices: list[int]) -> str:
    contiguous = indices == list(range(indices[0], indices[-1] + 1))
    return f"{indices[0]}..{indices[-1]}" if contiguous else f"{len(indices)} frames, " \
        f"{indices[0]} to {indices[-1]}"


def _create_sequence(gateway: Gateway, caller: Caller, body: JobCreate) -> Job:
    """A sequence job and one frame job per frame, then every frame's first stage queued at
    once (a group; completion is counted in the job store, `workers.sequence`)."""
    assert body.capture_id is not None and body.frames is not None
    with gateway.sessions() as session:
        capture = _ready_capture(session, caller, body.capture_id)
        indices = sequence_frames(capture, body.frames)
        options = _options(session, caller, body)
        parent = Job(id=new_id(), capture_id=capture.id, owner=caller.owner, options=options,
                     stages=list(SEQUENCE_STAGES), stage=SEQUENCE_STAGES[0], stage_timings={},
                     frames_total=len(indices), frames_done=0, frames_failed=0)
        frame_options = {k: v for k, v in options.items() if k != "frames"}
        frames = [Job(id=new_id(), capture_id=capture.id, owner=caller.owner,
                      options={**frame_options, "frame_index": i}, stages=[], stage_timings={},
                      parent_id=parent.id, frame_index=i) for i in indices]
        session.add_all([parent, *frames])
        session.commit()
        frame_ids = [f.id for f in frames]
    try:
        task_ids = gateway.send_group(TASK_STAGE, [[i, 0] for i in frame_ids], QUEUE_CPU)
    except Exception:
        _forget_job(gateway, parent.id)  # never queued: leave no job that would wait forever
        raise
    with gateway.sessions() as session:
        for frame_id, task_id in zip(frame_ids, task_ids, strict=True):
            session.execute(update(Job).where(Job.id == frame_id, Job.task_id.is_(None))
                            .values(task_id=task_id))
        session.commit()
        row = session.get(Job, parent.id)
        assert row is not None
        return row


@router.post("", status_code=202, response_model=JobPublic,
             summary="Queue a reconstruction (or a calibration)",
             responses={**located(202, "The job, queued."), **problem_responses(WRITE, BODY, {
                 404: "There is no such capture or rig (or another owner's).",
                 409: "The capture is still being validated (`capture-not-ready`).",
                 503: "The broker or the job store is unreachable; nothing was queued."})})
def create_job(body: JobCreate, response: Response, gateway: GatewayDep,
               caller: CallerDep) -> JobPublic:
    """The job belongs to the key's owner; it may use only captures and rigs the key sees."""
    job = _create(gateway, caller, body)
    response.headers["Location"] = f"{API_PREFIX}/jobs/{job.id}"
    return JobPublic.of(job, gateway.queues.get)


@router.get("", response_model=JobPage, summary="List jobs, newest first",
            responses=problem_responses(READ))
def list_jobs(session: SessionDep, caller: CallerDep, gateway: GatewayDep, limit: PageLimit = 20,
              offset: PageOffset = 0, state: JobState | None = None,
              capture_id: Annotated[str | None, Query(pattern=ID_PATTERN)] = None,
              parent_id: Annotated[str | None, Query(
                  pattern=ID_PATTERN, description="List the frame jobs of this sequence job "
                  "(default: top-level jobs only).")] = None) -> JobPage:
    query = select(Job) if caller.admin else select(Job).where(Job.owner == caller.owner)
    query = query.where(Job.parent_id.is_(None) if parent_id is None
                        else Job.parent_id == parent_id)
    if state is not None:
        query = query.where(Job.state == state)
    if capture_id is not None:
        query = query.where(Job.capture_id == capture_id)
    order = (Job.frame_index, Job.id) if parent_id else (Job.created_at.desc(), Job.id)
    rows, total = fetch_page(session, query, order, limit, offset)
    return JobPage(items=[JobPublic.of(r, gateway.queues.get) for r in rows], total=total,
                   limit=limit, offset=offset)


_JOB_BY_ID = select(Job.__table__).where(Job.__table__.c.id == bindparam("job_id"))


@router.get("/{job_id}", response_model=JobPublic, responses=problem_responses(READ, _NO_JOB))
async def get_job(job_id: JobId, gateway: GatewayDep, credentials: BearerDep) -> Response:
    # The hottest endpoint (clients poll it), kept lean: no thread hop (the key and job reads
    # take well under a millisecond each, so they run on the event loop), compiled Core
    # queries instead of the ORM, and one serialisation.
    caller = authenticate(gateway, credentials)
    with gateway.engine.connect() as conn:
        row = conn.execute(_JOB_BY_ID, {"job_id": job_id}).first()
    if row is None or not caller.sees(row.owner):
        raise _not_found(job_id)
    # A job that waits looks up the consumed queues, cached for a couple of seconds.
    return Response(JobPublic.of(row, gateway.queues.get).model_dump_json(),
                    media_type="application/json")


@router.delete("/{job_id}", response_model=JobPublic, summary="Cancel a job",
               responses=problem_responses(WRITE, _NO_JOB, {
                   409: "The job has already succeeded or failed (`job-finished`)."}))
def cancel_job(job_id: JobId, gateway: GatewayDep, caller: CallerDep) -> JobPublic:
    """Stops the job: a queued stage never starts, a running one stops at its next progress
    report (or at its end); artifacts already computed are kept for later jobs."""
    with gateway.sessions() as session:
        row = session.get(Job, job_id, with_for_update=True)
        if row is None or not caller.sees(row.owner):
            raise _not_found(job_id)
        if row.state in ("succeeded", "failed"):
            raise ProblemError(409, f"Job {job_id} has already {row.state}; nothing to cancel.",
                               kind="job-finished")
        if row.state != "cancelled":
            now = utcnow()
            row.state, row.updated_at, row.finished_at = "cancelled", now, now
            revoked = [row.task_id] if row.task_id else []
            revoked += _cancel_frames(session, job_id, now)
            session.commit()
            for task_id in revoked:
                gateway.revoke(task_id)
            if row.parent_id:  # one frame of a sequence: the sequence counts it as failed
                frame_over(gateway.sessions, job_id, gateway.send_task)
        return JobPublic.of(row)


def _cancel_frames(session: Session, parent_id: str, now: Any) -> list[str]:
    """Cancel a sequence's live frame jobs; their task ids (to revoke)."""
    live = (Job.parent_id == parent_id, Job.state.in_(("queued", "running")))
    task_ids = [t for t in session.scalars(select(Job.task_id).where(*live)) if t]
    session.execute(update(Job).where(*live).values(state="cancelled", updated_at=now,
                                                    finished_at=now, frame_counted=True))
    return task_ids


def _snapshot(gateway: Gateway, job_id: str, caller: Caller) -> JobPublic | None:
    with gateway.sessions() as session:
        row = session.get(Job, job_id)
        if row is None or not caller.sees(row.owner):
            return None
        return JobPublic.of(row, gateway.queues.get)


async def _events(request: Request, gateway: Gateway, caller: Caller, first: JobPublic
                  ) -> AsyncIterator[str]:
    last = ""
    current: JobPublic | None = first
    quiet_since = time.monotonic()
    while current is not None:
        data = current.model_dump_json()
        if data != last:
            last = data
            quiet_since = time.monotonic()
            yield f"event: job\nid: {current.updated_at.timestamp() if current.updated_at else 0}"\
                  f"\ndata: {data}\n\n"
            if current.state in TERMINAL_STATES:
                return
        elif time.monotonic() - quiet_since > EVENT_KEEPALIVE_S:
            quiet_since = time.monotonic()
            yield ": keep-alive\n\n"
        if await request.is_disconnected():
            return
        await asyncio.sleep(EVENT_POLL_S)
        current = await run_in_threadpool(_snapshot, gateway, first.id, caller)


@router.get("/{job_id}/events", summary="Job progress as server-sent events",
            response_class=StreamingResponse, responses={
                200: {"content": {"text/event-stream": {"schema": _EVENT_STREAM}},
                      "description": "`event: job` with the job as JSON on every change; the "
                                     "stream ends once the job has finished."},
                **problem_responses(READ, _NO_JOB)})
async def job_events(job_id: JobId, request: Request, gateway: GatewayDep,
                     caller: CallerDep) -> StreamingResponse:
    first = await run_in_threadpool(_snapshot, gateway, job_id, caller)
    if first is None:
        raise _not_found(job_id)
    return StreamingResponse(_events(request, gateway, caller, first),
                             media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})


