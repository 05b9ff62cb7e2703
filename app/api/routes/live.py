"""A stream's live point-cloud previews: PUT /streams/{id}/preview from the agent, relayed at
once to every viewer of WebSocket /streams/{id}/preview.

The agent sends each preview beside its frame-sets, not behind them, so a viewer sees the rig
as it is now even while frame-sets wait in the agent's spool; nothing of a preview is stored.

Browsers cannot set headers on a WebSocket, so the client's first message is the key, as text
``{"key": "<api key>"}`` within ``FIRST_MESSAGE_S``; the server closes with 4401 for a missing
or bad key and 4404 for a stream the key does not see. Then each newer ``preview.bin`` is one
binary message, exactly as the agent sent it (latest wins: `app.core.live`), and a text
message ``{"state": ...}`` each time the stream's state changes after receiving; the server
closes (1000) once the stream is closed (the message carries ``capture_id``) or failed.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import re
import time
from dataclasses import dataclass

from fastapi import APIRouter, Request, Response, WebSocket
from sqlalchemy import bindparam, select
from starlette.concurrency import run_in_threadpool
from starlette.websockets import WebSocketDisconnect

from app.api.deps import CallerDep, GatewayDep
from app.api.routes.streams import StreamId
from app.core.context import Gateway
from app.core.live import FINAL_STATES, PreviewHub, StateChange, Subscription, check_preview
from app.core.live_publish import publish_preview
from app.core.problems import WRITE, ProblemError, problem_responses
from app.core.security import Caller, find_caller
from app.core.streams import load_stream
from app.schemas import ID_PATTERN
from workers.models import Stream

router = APIRouter(prefix="/streams", tags=["streams"])
log = logging.getLogger(__name__)

FIRST_MESSAGE_S = 5.0
STATE_POLL_S = 1.0
"""How often a connection reads the stream's state from the job store (the worker that
assembles a capture, or another gateway, changes it where this hub cannot hear)."""
CLOSE_BAD_KEY = 4401
CLOSE_NO_STREAM = 4404
_GONE = (WebSocketDisconnect, OSError, RuntimeError)
"""What sending to a client that went away raises (uvicorn's ClientDisconnected is an
OSError; Starlette raises RuntimeError once the socket is closed)."""

_T = Stream.__table__.c
_STREAM_BY_ID = select(_T.owner, _T.state, _T.capture_id, _T.error).where(
    _T.id == bindparam("stream_id"))


@dataclass(frozen=True)
class _Snapshot:
    owner: str
    change: StateChange


def _read_stream(gateway: Gateway, stream_id: str) -> _Snapshot | None:
    with gateway.engine.connect() as conn:
        row = conn.execute(_STREAM_BY_ID, {"stream_id": stream_id}).first()
    if row is None:
        return None
    return _Snapshot(row.owner, StateChange(row.state, row.capture_id, row.error))


_PREVIEW_BODY: dict[str, object] = {"requestBody": {
    "required": True,
    "description": "One preview.bin (volumesh.preview/1, docs/api.md): a downsampled fused "
                   "point cloud of the frame-set just captured.",
    "content": {"application/octet-stream": {"schema": {"type": "string", "format": "binary"}}}}}


@router.put("/{stream_id}/preview", status_code=204, openapi_extra=_PREVIEW_BODY,
            summary="Send the stream's live preview",
            responses={204: {"description": "Relayed to the stream's viewers (or dropped as "
                                             "older than the last one relayed)."},
                       **problem_responses(WRITE, {
                           404: "There is no such stream (or another owner's).",
                           409: "The stream no longer takes frame-sets "
                                "(`stream-not-receiving`).",
                           413: "Larger than any well-formed preview (`body-too-large`).",
                           422: "Not a well-formed preview.bin (`invalid-preview`)."})})
async def put_preview(stream_id: StreamId, request: Request, gateway: GatewayDep,
                      caller: CallerDep) -> Response:
    """Relays the preview at once to the stream's viewers on every gateway; stores nothing.
    A preview of an earlier frame than the last one relayed is dropped."""
    stream = await run_in_threadpool(load_stream, gateway, caller, stream_id)
    if stream.state != "receiving":
        raise ProblemError(409, f"Stream {stream_id} is {stream.state}: it takes no more "
                           "previews.", kind="stream-not-receiving")
    data = await request.body()
    try:
        frame_index = check_preview(data)
    except ValueError as exc:
        raise ProblemError(422, f"preview.bin: {exc}", kind="invalid-preview") from None
    publish_preview(request.app, stream_id, frame_index, data)
    return Response(status_code=204)


@router.websocket("/{stream_id}/preview", name="stream_preview")
async def stream_preview(websocket: WebSocket, stream_id: str) -> None:
    # Accepted first: a close before the handshake reaches a browser as a bare failure, with
    # no code to tell a bad key from a missing stream.
    await websocket.accept()
    gateway: Gateway = websocket.app.state.gateway
    caller = await _caller(websocket, gateway)
    if caller is None:
        await _close(websocket, CLOSE_BAD_KEY, 'send a live API key first: {"key": "..."}')
        return
    snapshot = None
    if re.fullmatch(ID_PATTERN, stream_id):
        snapshot = await run_in_threadpool(_read_stream, gateway, stream_id)
    if snapshot is None or not caller.sees(snapshot.owner):
        await _close(websocket, CLOSE_NO_STREAM, f"there is no stream {stream_id[:40]}")
        return
    hub: PreviewHub = websocket.app.state.previews
    async with hub.subscribe(stream_id) as subscription:
        relay = asyncio.create_task(_relay(websocket, gateway, stream_id, subscription,
                                           snapshot.change))
        listen = asyncio.create_task(_until_disconnect(websocket))
        done, pending = await asyncio.wait({relay, listen}, return_when=asyncio.FIRST_COMPLETED)
        for task in pending:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError, *_GONE):
                await task
    if relay not in done:
        return  # the client went away
    if relay.exception() is not None:
        log.error("live preview of stream %s failed", stream_id, exc_info=relay.exception())
        await _close(websocket, 1011, "the gateway failed; reconnect")
    elif relay.result():
        await _close(websocket, 1000, "the stream stopped")


async def _caller(websocket: WebSocket, gateway: Gateway) -> Caller | None:
    """The caller whose key is the first message, or None (no, malformed or unknown key)."""
    try:
        message = await asyncio.wait_for(websocket.receive(), FIRST_MESSAGE_S)
    except TimeoutError:
        return None
    try:
        key = json.loads(message.get("text") or "")["key"]
    except (ValueError, TypeError, KeyError):
        return None
    if not isinstance(key, str) or not key:
        return None
    return find_caller(gateway.engine, key)  # one indexed read, on the loop like the routes'


async def _relay(websocket: WebSocket, gateway: Gateway, stream_id: str,
                 subscription: Subscription, first: StateChange) -> bool:
    """Sends previews and state changes until the stream is closed or failed (True) or the
    client goes away (False)."""
    sent_state = "receiving"
    change: StateChange | None = first
    polled_at = time.monotonic()
    try:
        while True:
            # The job store may lag the hub's word for a moment: never back to receiving.
            if change is not None and change.state not in (sent_state, "receiving"):
                await websocket.send_text(change.message())
                sent_state = change.state
                if sent_state in FINAL_STATES:
                    return True
            change = None
            message = await subscription.next(STATE_POLL_S)
            if isinstance(message, bytes):
                await websocket.send_bytes(message)
            elif isinstance(message, StateChange):
                change = message
            if time.monotonic() - polled_at >= STATE_POLL_S:
                polled_at = time.monotonic()
                snapshot = await run_in_threadpool(_read_stream, gateway, stream_id)
                if snapshot is None:
                    return True  # deleted
                change = change or snapshot.change
    except _GONE:
        return False


async def _until_disconnect(websocket: WebSocket) -> None:
    # Later client messages mean nothing; reading them is how a disconnect is noticed.
    while (await websocket.receive())["type"] != "websocket.disconnect":
        pass


async def _close(websocket: WebSocket, code: int, reason: str) -> None:
    with contextlib.suppress(*_GONE):
        await websocket.close(code, reason)
