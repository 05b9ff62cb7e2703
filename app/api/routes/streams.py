"""POST /streams, GET /streams, GET /streams/{id}, PUT /streams/{id}/frames/{index},
POST /streams/{id}/close: a capture sent frame-set by frame-set while it is recorded.

Each frame-set is checked in memory, stored as it came and counted once per index; closing the
stream queues ``volumesh.assemble_stream`` (queue ``validate``), which writes the frame-sets
into one capture zip, reads it whole like an upload and sets the stream's ``capture_id``.
"""

from __future__ import annotations

import logging
from typing import Annotated, Any

from fastapi import APIRouter, Header, Path, Query, Request, Response
from sqlalchemy import select
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool
from starlette.requests import ClientDisconnect

from app.api.deps import CallerDep, GatewayDep, SessionDep
from app.api.pagination import PageLimit, PageOffset, fetch_page
from app.api.routes.rigs import find_rig
from app.core.framesets import check_frame_set
from app.core.live_publish import publish_state
from app.core.metrics import UPLOAD_BYTES_KEY
from app.core.problems import BODY, READ, WRITE, ProblemError, located, problem_responses
from app.core.security import Caller
from app.core.streams import close_stream, load_stream, reopen_stream, store_frame
from app.core.uploads import ZIP_TYPES
from app.schemas import API_PREFIX, ID_PATTERN
from app.stream_schemas import (
    FrameSetPublic,
    StreamCamera,
    StreamCreate,
    StreamPage,
    StreamPublic,
    StreamState,
)
from workers.celery_app import QUEUE_VALIDATE, TASK_ASSEMBLE
from workers.models import Stream, new_id
from workers.settings import Settings

router = APIRouter(prefix="/streams", tags=["streams"])
log = logging.getLogger(__name__)

StreamId = Annotated[str, Path(pattern=ID_PATTERN, description="A stream id.")]
FrameIndex = Annotated[int, Path(ge=0, le=999_999, description="The frame index.")]
TimestampUs = Annotated[int, Header(alias="Volumesh-Timestamp-Us", ge=0, le=2**63 - 1,
                                    description="The frame-set's device timestamp, µs.")]
_NO_STREAM = {404: "There is no such stream (or another owner's)."}
_FRAME_SET_BODY: dict[str, Any] = {"requestBody": {
    "required": True,
    "description": "One frame-set: a zip of <camera>/depth/<index>.png (16-bit greyscale, "
                   "every camera) and optional <camera>/color/<index>.jpg (or .png).",
    "content": {media: {"schema": {"type": "string", "format": "binary"}}
                for media in ("application/zip", "application/octet-stream")}}}
_FRAME_SET_PROBLEMS = {
    400: "The client disconnected mid-body (`upload-interrupted`).",
    408: "The body stopped arriving for `VOLUMESH_UPLOAD_IDLE_TIMEOUT_S` (`body-timeout`).",
    409: "The stream no longer takes frame-sets (`stream-not-receiving`).",
    413: "Over `VOLUMESH_MAX_FRAME_SET_BYTES` (`body-too-large`, `frame-set-too-large`).",
    415: "Another Content-Type (`unsupported-media-type`).",
    422: "A malformed frame-set (`invalid-frame-set`, naming the entry) or parameter.",
}


def _poses_from_rig(session: Session, caller: Caller, body: StreamCreate
                    ) -> list[StreamCamera]:
    if body.rig_id is None:
        return body.cameras
    poses = find_rig(session, caller, body.rig_id).document.get("world_from_depth", {})
    missing = [camera.id for camera in body.cameras if camera.id not in poses]
    if missing:
        raise ProblemError(422, f"cameras: camera {missing[0]} has no pose in rig "
                           f"{body.rig_id}.", kind="validation-error")
    return [camera.model_copy(update={"world_from_depth": poses[camera.id]})
            for camera in body.cameras]


def _check_pixels(cameras: list[StreamCamera], settings: Settings) -> None:
    for camera in cameras:
        for name in ("depth_intrinsics", "color_intrinsics"):
            intrinsics = getattr(camera, name)
            if intrinsics is not None and intrinsics.pixels > settings.max_image_pixels:
                raise ProblemError(422, f"cameras: camera {camera.id}: {name} has "
                                   f"{intrinsics.pixels} pixels, more than "
                                   f"{settings.max_image_pixels} (VOLUMESH_MAX_IMAGE_PIXELS).",
                                   kind="validation-error")


@router.post("", status_code=201, response_model=StreamPublic, summary="Start a stream",
             responses={**located(201, "The stream, receiving."),
                        **problem_responses(WRITE, BODY, {
                            404: "There is no such rig (or another owner's).",
                            422: "A bad body (`validation-error`): the detail names the camera "
                                 "and field (intrinsics, a pose that is not rigid, a camera the "
                                 "rig has no pose for)."})})
def create_stream(body: StreamCreate, response: Response, session: SessionDep,
                  gateway: GatewayDep, caller: CallerDep) -> StreamPublic:
    """A stream takes frame-sets of these cameras until it is closed; it belongs to the key's
    owner. With `rig_id`, every camera's `world_from_depth` is the rig's."""
    _check_pixels(body.cameras, gateway.settings)
    cameras = _poses_from_rig(session, caller, body)
    row = Stream(id=new_id(), owner=caller.owner, name=body.name, state="receiving",
                 fps=body.fps, depth_scale=body.depth_scale, rig_id=body.rig_id,
                 cameras=[camera.model_dump() for camera in cameras], frames_received=0)
    session.add(row)
    session.commit()
    response.headers["Location"] = f"{API_PREFIX}/streams/{row.id}"
    return StreamPublic.of(row)


@router.get("", response_model=StreamPage, summary="List streams, newest first",
            responses=problem_responses(READ))
def list_streams(session: SessionDep, caller: CallerDep, limit: PageLimit = 20,
                 offset: PageOffset = 0,
                 state: Annotated[StreamState | None, Query(description="Only streams in "
                                                                        "this state.")] = None
                 ) -> StreamPage:
    query = select(Stream) if caller.admin else select(Stream).where(Stream.owner == caller.owner)
    if state is not None:
        query = query.where(Stream.state == state)
    rows, total = fetch_page(session, query, (Stream.created_at.desc(), Stream.id), limit,
                             offset)
    return StreamPage(items=[StreamPublic.of(r) for r in rows], total=total, limit=limit,
                      offset=offset)


@router.get("/{stream_id}", response_model=StreamPublic,
            responses=problem_responses(READ, _NO_STREAM))
async def get_stream(stream_id: StreamId, gateway: GatewayDep,
                     caller: CallerDep) -> StreamPublic:
    return StreamPublic.of(await run_in_threadpool(load_stream, gateway, caller, stream_id))


async def _read_body(request: Request, limit: int) -> bytes:
    """The whole body, refused past ``limit`` bytes as it arrives (a frame-set is checked in
    memory; the limit bounds that memory)."""
    media = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if media not in ZIP_TYPES:
        raise ProblemError(415, f"Content-Type {media or 'none'!r} is not accepted: send the "
                           "frame-set as application/zip.", kind="unsupported-media-type")
    chunks: list[bytes] = []
    size = 0
    try:
        async for chunk in request.stream():
            size += len(chunk)
            if size > limit:
                raise ProblemError(413, f"The frame-set is larger than the limit of {limit} "
                                   "bytes (VOLUMESH_MAX_FRAME_SET_BYTES).",
                                   kind="frame-set-too-large")
            chunks.append(chunk)
    except ClientDisconnect:
        raise ProblemError(400, "The client disconnected before the frame-set arrived whole; "
                           "nothing was stored.", kind="upload-interrupted") from None
    return b"".join(chunks)


@router.put("/{stream_id}/frames/{index}", status_code=201, response_model=FrameSetPublic,
            openapi_extra=_FRAME_SET_BODY, summary="Send one frame-set",
            responses={201: {"description": "Stored: the first time this index arrived."},
                       200: {"model": FrameSetPublic,
                             "description": "A re-send of an index already stored; nothing "
                                            "changed."},
                       **problem_responses(WRITE, _NO_STREAM, _FRAME_SET_PROBLEMS)})
async def put_frame_set(stream_id: StreamId, index: FrameIndex, request: Request,
                        response: Response, gateway: GatewayDep, caller: CallerDep,
                        timestamp_us: TimestampUs = 0) -> FrameSetPublic:
    """Stores the frame-set before answering. Either answer (201 stored, 200 a re-send)
    means it is acknowledged: the client may delete it. Retry on connection errors, 5xx, 408
    and 429 only."""
    stream = await run_in_threadpool(load_stream, gateway, caller, stream_id)
    limit = gateway.settings.max_frame_set_bytes
    body = await _read_body(request, limit)
    sizes = {c["id"]: (c["depth_intrinsics"]["width"], c["depth_intrinsics"]["height"])
             for c in stream.cameras}
    await run_in_threadpool(check_frame_set, body, index, sizes, 2 * limit)
    ack = await run_in_threadpool(store_frame, gateway, stream_id, index, timestamp_us, body)
    if ack.stored:
        # Counted by the metrics middleware only if the request ends accepted (2xx).
        setattr(request.state, UPLOAD_BYTES_KEY, len(body))
    else:
        response.status_code = 200
    return FrameSetPublic(stream_id=stream_id, index=index, stored=ack.stored,
                          frames_received=ack.frames_received)


@router.post("/{stream_id}/close", status_code=202, response_model=StreamPublic,
             summary="Close a stream and assemble its capture",
             responses={202: {"description": "Closed now: the capture is being assembled."},
                        200: {"model": StreamPublic,
                              "description": "Closed before: the stream as it is now."},
                        **problem_responses(WRITE, BODY, _NO_STREAM, {
                            409: "No frame-set arrived yet (`stream-empty`)."})})
async def close(stream_id: StreamId, request: Request, response: Response,
                gateway: GatewayDep, caller: CallerDep) -> StreamPublic:
    """Stops taking frame-sets; a worker writes them, in index order, into one capture (format
    v1), reads it whole and sets `capture_id` and state `closed` (or `failed` with why)."""
    row, moved = await run_in_threadpool(close_stream, gateway, caller, stream_id)
    if not moved:
        response.status_code = 200
        return StreamPublic.of(row)
    try:
        await run_in_threadpool(gateway.send_task, TASK_ASSEMBLE, [stream_id], QUEUE_VALIDATE)
    except Exception:
        await run_in_threadpool(reopen_stream, gateway, stream_id)  # never assembled otherwise
        raise
    try:
        publish_state(request.app, stream_id, row.state)
    except Exception:  # viewers also read the state from the job store
        log.warning("stream %s: state change not published", stream_id, exc_info=True)
    return StreamPublic.of(row)
