"""A stream in the job store, on SQLite and PostgreSQL: frame-sets sent at once by many
gateways' threads each counted once (`app.core.streams`), and the closed stream's assembly
(`workers.streams`): one capture with every frame, the same capture when a run is redelivered
or runs again after dying midway, a failed stream naming the damaged file, and frame-sets kept
in object storage."""

from __future__ import annotations

import threading
from collections.abc import Iterable
from pathlib import Path

import pytest
from sqlalchemy import func, select

from app.core.context import Gateway
from app.core.streams import FrameAck, store_frame
from tests.frame_sets import CAMERAS, camera, frame_entries, frame_set, pack
from tests.integration.services import MotoS3
from workers.context import WorkerContext
from workers.models import Capture, CaptureGrant, Stream, StreamFrame, new_id
from workers.settings import Settings
from workers.streams import assemble_stream

OWNER = "key:streamer"


@pytest.fixture
def ctx(store_settings: Settings) -> WorkerContext:
    return WorkerContext.create(store_settings)


def _put_chunks(ctx: WorkerContext, stream_id: str, bodies: dict[int, bytes]) -> None:
    for index, body in bodies.items():
        ctx.storage.put_bytes(f"streams/{stream_id}/{index:06d}.zip", body)


def _stream(ctx: WorkerContext, bodies: dict[int, bytes], state: str = "assembling") -> str:
    """A stream (by default one its client has closed) with these frame-sets stored and
    counted."""
    stream_id = new_id()
    _put_chunks(ctx, stream_id, bodies)
    with ctx.store.sessions.begin() as session:
        session.add(Stream(id=stream_id, owner=OWNER, state=state, fps=30.0,
                           depth_scale=0.001, cameras=[camera(c) for c in CAMERAS],
                           frames_received=len(bodies),
                           last_frame_index=max(bodies, default=None)))
        session.flush()
        for index, body in bodies.items():
            session.add(StreamFrame(stream_id=stream_id, frame_index=index,
                                    timestamp_us=40_000 * index, size_bytes=len(body),
                                    storage_key=f"streams/{stream_id}/{index:06d}.zip"))
    return stream_id


def _row(ctx: WorkerContext, stream_id: str) -> Stream:
    with ctx.store.sessions() as session:
        row = session.get(Stream, stream_id)
        assert row is not None
        return row


def _captures(ctx: WorkerContext) -> int:
    with ctx.store.sessions() as session:
        return session.scalar(select(func.count()).select_from(Capture)) or 0


def _chunks_left(ctx: WorkerContext, stream_id: str, indices: Iterable[int]) -> list[int]:
    return [i for i in indices if ctx.storage.exists(f"streams/{stream_id}/{i:06d}.zip")]


def test_a_stream_assembles_once_and_again_into_the_same_capture(ctx: WorkerContext) -> None:
    bodies = {i: frame_set(i, color=i == 0) for i in (0, 3, 1)}
    stream_id = _stream(ctx, bodies)
    assemble_stream(ctx, stream_id)
    closed = _row(ctx, stream_id)
    assert (closed.state, closed.error) == ("closed", None)
    with ctx.store.sessions() as session:
        capture = session.get(Capture, closed.capture_id)
        assert capture is not None and capture.state == "ready"
        assert (capture.cameras, capture.frame_indices) == (2, [0, 1, 3])
        assert session.get(CaptureGrant, (capture.id, OWNER)) is not None
    assert _chunks_left(ctx, stream_id, bodies) == []

    assemble_stream(ctx, stream_id)  # a redelivery finds the stream closed
    assert _row(ctx, stream_id).updated_at == closed.updated_at
    assert _captures(ctx) == 1

    # A run that died after storing the capture, before closing the stream, runs again:
    # the same frame-sets give the same bytes, so the same capture, stored once.
    with ctx.store.sessions.begin() as session:
        row = session.get(Stream, stream_id)
        assert row is not None
        row.state, row.capture_id = "assembling", None
    _put_chunks(ctx, stream_id, bodies)
    assemble_stream(ctx, stream_id)
    again = _row(ctx, stream_id)
    assert (again.state, again.capture_id) == ("closed", closed.capture_id)
    assert _captures(ctx) == 1
    assert _chunks_left(ctx, stream_id, bodies) == []


def _damaged_png(data: bytes) -> bytes:
    at = len(data) - 20  # inside the image data, before IEND: its CRC no longer matches
    return data[:at] + bytes([data[at] ^ 0xFF]) + data[at + 1:]


def test_a_damaged_frame_set_fails_the_stream_naming_the_file(ctx: WorkerContext) -> None:
    entries = frame_entries(1)
    entries["cam1/depth/000001.png"] = _damaged_png(entries["cam1/depth/000001.png"])
    bodies = {0: frame_set(0), 1: pack(entries)}
    stream_id = _stream(ctx, bodies)
    assemble_stream(ctx, stream_id)
    failed = _row(ctx, stream_id)
    assert failed.state == "failed" and failed.capture_id is None
    assert "cam1/depth/000001.png" in (failed.error or "")
    assert _captures(ctx) == 0
    assert _chunks_left(ctx, stream_id, bodies) == []


def test_frame_sets_in_object_storage_assemble(moto: MotoS3, tmp_path: Path) -> None:
    ctx = WorkerContext.create(Settings.model_validate(
        {"data_dir": tmp_path, **moto.settings("volumesh-test")}))
    bodies = {i: frame_set(i) for i in range(3)}
    stream_id = _stream(ctx, bodies)
    assemble_stream(ctx, stream_id)
    closed = _row(ctx, stream_id)
    assert (closed.state, closed.error) == ("closed", None)
    assert _chunks_left(ctx, stream_id, bodies) == []
    assert not list((tmp_path / "tmp" / "streams").iterdir())  # no zip, no copies left


def test_frame_sets_sent_at_once_count_once(store_settings: Settings) -> None:
    gateways = [Gateway.create(store_settings) for _ in range(3)]  # as several processes
    ctx = WorkerContext.create(store_settings)
    stream_id = _stream(ctx, {}, state="receiving")
    acks: list[FrameAck] = []
    barrier = threading.Barrier(6)

    def send(gateway: Gateway) -> None:
        barrier.wait()
        for index in (4, 1, 3, 0, 2):
            acks.append(store_frame(gateway, stream_id, index, index, frame_set(index)))

    threads = [threading.Thread(target=send, args=(g,)) for g in gateways * 2]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    counted = _row(ctx, stream_id)
    assert (counted.frames_received, counted.last_frame_index) == (5, 4)
    assert sum(ack.stored for ack in acks) == 5 and len(acks) == 30
    with ctx.store.sessions() as session:
        rows = session.scalars(select(StreamFrame.frame_index)
                               .where(StreamFrame.stream_id == stream_id)).all()
    assert sorted(rows) == [0, 1, 2, 3, 4]
    for gateway in gateways:
        gateway.close()
