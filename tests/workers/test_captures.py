"""An upload's validation in the worker ends every capture ready or rejected with a message,
whatever the reader does: damaged members, PNG bombs, a reader that crashes, a storage that
stays down."""

from __future__ import annotations

import hashlib
import io
import time
import zipfile
from pathlib import Path

import pytest

from tests.hostile_captures import bomb_capture_zip, damaged_member_zip
from tests.integration.services import make_capture_zip
from workers import captures
from workers.captures import capture_limits, validate_capture
from workers.context import WorkerContext
from workers.models import Capture
from workers.settings import Settings


@pytest.fixture(scope="module")
def valid_zip(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    folder = tmp_path_factory.mktemp("captures")
    return make_capture_zip(folder, cameras=2, width=64, height=48).read_bytes()


@pytest.fixture
def ctx(tmp_path: Path) -> WorkerContext:
    return WorkerContext.create(Settings(data_dir=tmp_path))


def _stored(ctx: WorkerContext, data: bytes) -> str:
    """Stores ``data`` as an upload the gateway has just registered; returns its id."""
    sha256 = hashlib.sha256(data).hexdigest()
    ctx.storage.put_bytes(f"captures/{sha256}.zip", data)
    with ctx.store.sessions.begin() as session:
        session.add(Capture(id=sha256[:32], sha256=sha256, size_bytes=len(data),
                            storage_key=f"captures/{sha256}.zip", state="validating"))
    return sha256[:32]


def _outcome(ctx: WorkerContext, capture_id: str) -> tuple[str, str | None]:
    with ctx.store.sessions() as session:
        row = session.get(Capture, capture_id)
        assert row is not None
        return row.state, row.error


def _entries(data: bytes) -> dict[str, bytes]:
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        return {name: archive.read(name) for name in archive.namelist()}


def test_a_valid_capture_is_ready(ctx: WorkerContext, valid_zip: bytes) -> None:
    capture_id = _stored(ctx, valid_zip)
    validate_capture(ctx, capture_id)
    assert _outcome(ctx, capture_id) == ("ready", None)


def test_a_damaged_member_rejects_the_capture_naming_it(ctx: WorkerContext,
                                                        valid_zip: bytes) -> None:
    member = "cam1/depth/000000.png"
    capture_id = _stored(ctx, damaged_member_zip(_entries(valid_zip), member, "crc"))
    validate_capture(ctx, capture_id)
    state, error = _outcome(ctx, capture_id)
    assert state == "rejected" and error is not None and error.startswith(f"{member}: ")


def test_a_png_bomb_is_rejected_at_once(ctx: WorkerContext) -> None:
    capture_id = _stored(ctx, bomb_capture_zip())
    started = time.perf_counter()
    validate_capture(ctx, capture_id)
    assert time.perf_counter() - started < 2.0
    state, error = _outcome(ctx, capture_id)
    assert state == "rejected" and error is not None
    assert "12000x12000 is 144000000 pixels, over the limit of 25000000" in error


def test_a_crashing_reader_still_rejects_the_capture(ctx: WorkerContext, valid_zip: bytes,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    def crash(path: Path, limits: object) -> tuple[int, int]:
        raise MemoryError("decoder ran out")

    monkeypatch.setattr(captures, "read_whole", crash)
    capture_id = _stored(ctx, valid_zip)
    validate_capture(ctx, capture_id)
    assert _outcome(ctx, capture_id) == (
        "rejected", "the capture could not be read (MemoryError: decoder ran out)")


def test_a_task_that_fails_outside_the_reader_rejects_the_capture(
        tmp_path: Path, valid_zip: bytes, monkeypatch: pytest.MonkeyPatch) -> None:
    from workers import tasks

    monkeypatch.setenv("VOLUMESH_DATA_DIR", str(tmp_path))
    monkeypatch.setenv("VOLUMESH_TASK_MAX_RETRIES", "0")
    monkeypatch.setattr(tasks.validate.app, "volumesh_settings", None, raising=False)
    ctx = WorkerContext.create(Settings())
    storage_down = _stored(ctx, valid_zip)
    broken = _stored(ctx, valid_zip + b"-")

    def fail(_ctx: WorkerContext, capture_id: str) -> None:
        raise (OSError("storage unreachable") if capture_id == storage_down
               else KeyError("bug"))

    monkeypatch.setattr(tasks, "validate_capture", fail)
    tasks.validate(storage_down)
    tasks.validate(broken)
    assert _outcome(ctx, storage_down) == (
        "rejected", "the worker could not fetch the stored capture after 0 retries "
        "(OSError: storage unreachable); upload it again")
    assert _outcome(ctx, broken) == (
        "rejected", "internal error while validating the capture (KeyError: 'bug')")


def test_the_reader_gets_the_settings_limits() -> None:
    limits = capture_limits(Settings(max_image_pixels=1234, max_capture_files=7))
    assert (limits.max_image_pixels, limits.max_files) == (1234, 7)


def test_the_pipeline_and_the_service_default_to_the_same_pixel_cap() -> None:
    from pipeline.io.capture_io import ArchiveLimits

    assert ArchiveLimits().max_image_pixels == Settings().max_image_pixels
