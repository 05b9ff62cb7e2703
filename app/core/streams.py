"""The gateway's side of a stream in the job store: finding one, counting a frame-set once,
closing it. Several gateways may take frames of one stream, so every change is one
conditional UPDATE or INSERT that the database settles (docs/api.md, Streams)."""

from __future__ import annotations

from dataclasses import dataclass

from sqlalchemy import DateTime, Integer, bindparam, case, insert, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app.core.context import Gateway
from app.core.problems import ProblemError
from app.core.security import Caller
from workers.models import Stream, StreamFrame, utcnow

RECEIVING = "receiving"


def chunk_key(stream_id: str, index: int) -> str:
    """Where a stream's frame-set is stored (as the workers' `workers.streams` reads it)."""
    return f"streams/{stream_id}/{index:06d}.zip"


def find_stream(session: Session, caller: Caller, stream_id: str) -> Stream:
    """The caller's stream, or a 404 (another owner's stream is answered as a missing one)."""
    row = session.get(Stream, stream_id)
    if row is None or not caller.sees(row.owner):
        raise ProblemError(404, f"There is no stream {stream_id}; start one with POST "
                           "/api/v1/streams.", kind="not-found")
    return row


def load_stream(gateway: Gateway, caller: Caller, stream_id: str) -> Stream:
    with gateway.sessions() as session:
        return find_stream(session, caller, stream_id)


def _not_receiving(stream_id: str, state: str | None) -> ProblemError:
    return ProblemError(409, f"Stream {stream_id} is {state}: it takes no more frame-sets.",
                        kind="stream-not-receiving")


@dataclass(frozen=True)
class FrameAck:
    stored: bool
    """False for a re-send of an index already stored."""
    frames_received: int


def _received(session: Session, stream_id: str) -> int:
    return session.scalar(select(Stream.frames_received).where(Stream.id == stream_id)) or 0


_FIRST_LOOK = select(
    Stream.state, Stream.frames_received,
    select(StreamFrame.frame_index).where(StreamFrame.stream_id == bindparam("stream_id"),
                                          StreamFrame.frame_index == bindparam("index")).exists()
).where(Stream.id == bindparam("stream_id"))
"""(state, count, whether the index is stored): built once, as the two below (building a
statement costs more than SQLite takes to run it)."""
_INDEX, _NOW = bindparam("index", type_=Integer), bindparam("now", type_=DateTime(timezone=True))
_COUNT = (update(Stream).where(Stream.id == bindparam("stream_id"), Stream.state == RECEIVING)
          .values(frames_received=Stream.frames_received + 1, updated_at=_NOW,
                  last_frame_index=case(
                      (Stream.last_frame_index.is_(None), _INDEX),
                      (Stream.last_frame_index < _INDEX, _INDEX),
                      else_=Stream.last_frame_index))
          .returning(Stream.frames_received))
_ADD = insert(StreamFrame)


def _first_look(session: Session, stream_id: str, index: int) -> tuple[str | None, int, bool]:
    """(the stream's state, its count, whether ``index`` is stored) in one query."""
    row = session.connection().execute(
        _FIRST_LOOK, {"stream_id": stream_id, "index": index}).one_or_none()
    return (None, 0, False) if row is None else (row[0], row[1] or 0, bool(row[2]))


def store_frame(gateway: Gateway, stream_id: str, index: int, timestamp_us: int,
                body: bytes) -> FrameAck:
    """Store frame-set ``index`` durably, then count it once: a re-send changes nothing, and
    once the stream left `receiving` no new index is counted (the assembly's set is fixed).
    Three statements a new frame-set (a look, the count, the row; one commit): each a round
    trip to the job store, 30 times a second per stream."""
    with gateway.sessions() as session:
        state, received, stored = _first_look(session, stream_id, index)
        if stored:
            return FrameAck(False, received)
        if state != RECEIVING:
            raise _not_receiving(stream_id, state)
    key = chunk_key(stream_id, index)
    gateway.storage.put_bytes(key, body)
    with gateway.sessions() as session:
        counted = _count(session, stream_id, index)
        if counted is None:
            session.rollback()
            return _closed_meanwhile(gateway, session, stream_id, index)
        try:
            session.connection().execute(_ADD, {
                "stream_id": stream_id, "frame_index": index, "timestamp_us": timestamp_us,
                "size_bytes": len(body), "storage_key": key})
            session.commit()
        except IntegrityError:  # the same index arrived twice at once: the other one counted
            session.rollback()
            return FrameAck(False, _received(session, stream_id))
        return FrameAck(True, counted)


def _count(session: Session, stream_id: str, index: int) -> int | None:
    """The stream's count after counting ``index``; None when it no longer receives. Core
    statements on the session's connection: the ORM's bookkeeping (synchronising the identity
    map, a unit of work for one row) cost more than the database did."""
    return session.connection().execute(
        _COUNT, {"stream_id": stream_id, "index": index, "now": utcnow()}).scalar()


def _closed_meanwhile(gateway: Gateway, session: Session, stream_id: str,
                      index: int) -> FrameAck:
    # The stream was closed between the first look and the count. No index can be counted
    # any more, so whether this one was (by a re-send) is settled.
    if session.get(StreamFrame, (stream_id, index)) is not None:
        return FrameAck(False, _received(session, stream_id))
    gateway.storage.delete(chunk_key(stream_id, index))  # nothing refers to it
    state = session.scalar(select(Stream.state).where(Stream.id == stream_id))
    raise _not_receiving(stream_id, state)


def close_stream(gateway: Gateway, caller: Caller, stream_id: str) -> tuple[Stream, bool]:
    """Move the stream from `receiving` to `assembling`; returns (the stream, whether this
    call moved it). 409 while no frame-set arrived."""
    with gateway.sessions() as session:
        row = find_stream(session, caller, stream_id)
        moved = session.execute(
            update(Stream).where(Stream.id == stream_id, Stream.state == RECEIVING,
                                 Stream.frames_received > 0)
            .values(state="assembling", updated_at=utcnow()))
        session.commit()
        session.refresh(row)
        if row.state == RECEIVING:
            raise ProblemError(409, f"Stream {stream_id} has no frame-set yet; send one with "
                               "PUT before closing it.", kind="stream-empty")
        return row, bool(moved.rowcount)  # type: ignore[attr-defined]


def reopen_stream(gateway: Gateway, stream_id: str) -> None:
    """Undo a close whose assembly could not be queued, so that closing again queues it."""
    with gateway.sessions.begin() as session:
        session.execute(update(Stream).where(Stream.id == stream_id,
                                             Stream.state == "assembling")
                        .values(state=RECEIVING, updated_at=utcnow()))
