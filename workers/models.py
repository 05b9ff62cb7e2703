"""SQLAlchemy models of the job store: API keys, captures, jobs, assets, rigs and streams."""

from __future__ import annotations

import uuid
from datetime import UTC, datetime
from typing import Any

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    DateTime,
    Float,
    ForeignKey,
    Integer,
    String,
    Text,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column

JOB_STATES = ("queued", "running", "succeeded", "failed", "cancelled")
TERMINAL_STATES = frozenset({"succeeded", "failed", "cancelled"})
STREAM_STATES = ("receiving", "assembling", "closed", "failed")


def utcnow() -> datetime:
    return datetime.now(UTC)


def new_id() -> str:
    return uuid.uuid4().hex


class Base(DeclarativeBase):
    pass


class ApiKey(Base):
    """An API key; only its SHA-256 is stored (keys are 256-bit random, so no slow hash)."""

    __tablename__ = "api_keys"

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    name: Mapped[str] = mapped_column(String(100), index=True)
    prefix: Mapped[str] = mapped_column(String(16))
    """The key's first characters, shown by ``volumesh keys list`` to tell keys apart."""
    key_hash: Mapped[str] = mapped_column(String(64), unique=True, index=True)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    revoked_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True), default=None)
    project: Mapped[str | None] = mapped_column(String(100), default=None)
    """Keys of one project share what they make; unset: the key owns its work alone."""
    admin: Mapped[bool | None] = mapped_column(Boolean, default=False)
    """An admin key sees and acts on everything, and reads /metrics."""


class ServiceSecret(Base):
    """A random secret the gateways share through the job store (it signs asset share links)."""

    __tablename__ = "service_secrets"

    name: Mapped[str] = mapped_column(String(40), primary_key=True)
    value: Mapped[str] = mapped_column(String(128))
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)


class Capture(Base):
    """An uploaded capture zip, stored once per content (id = start of its SHA-256)."""

    __tablename__ = "captures"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    sha256: Mapped[str] = mapped_column(String(64), unique=True)
    size_bytes: Mapped[int] = mapped_column(Integer)
    storage_key: Mapped[str] = mapped_column(String(200))
    state: Mapped[str] = mapped_column(String(16), default="validating")
    """validating (a worker is reading it) | ready | rejected (error says why)."""
    error: Mapped[str | None] = mapped_column(Text, default=None)
    cameras: Mapped[int | None] = mapped_column(Integer, default=None)
    frames: Mapped[int | None] = mapped_column(Integer, default=None)
    frame_indices: Mapped[list[int] | None] = mapped_column(JSON, default=None)
    """The frames' indices as capture.json lists them (set when validated)."""
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)


class CaptureGrant(Base):
    """Who may use a capture. A capture is stored once per content, so an owner who uploads
    the same bytes as another is granted the same capture, and sees nothing of the other."""

    __tablename__ = "capture_grants"

    capture_id: Mapped[str] = mapped_column(ForeignKey("captures.id", ondelete="CASCADE"),
                                            primary_key=True)
    owner: Mapped[str] = mapped_column(String(120), primary_key=True, index=True)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow,
                                                 index=True)


class Job(Base):
    """One reconstruction of a capture; workers advance it stage by stage."""

    __tablename__ = "jobs"

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    capture_id: Mapped[str] = mapped_column(ForeignKey("captures.id"), index=True)
    owner: Mapped[str | None] = mapped_column(String(120), default=None, index=True)
    """Who owns it (and its asset): ``project:NAME`` for a key of a project, else ``key:ID``."""
    state: Mapped[str] = mapped_column(String(16), default="queued", index=True)
    stage: Mapped[str | None] = mapped_column(String(40), default=None)
    stage_index: Mapped[int] = mapped_column(Integer, default=0)
    """Index in ``stages`` of the stage now running (or last run)."""
    done_count: Mapped[int] = mapped_column(Integer, default=0)
    """Stages finished, whose successor has been queued; a task for an earlier index is a
    duplicate delivery and does nothing."""
    stages: Mapped[list[str]] = mapped_column(JSON, default=list)
    """The stages this job runs, in order (set by the first worker that picks it up)."""
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    stage_timings: Mapped[dict[str, float]] = mapped_column(JSON, default=dict)
    """Seconds each finished stage took (0 when its output was already stored)."""
    error: Mapped[str | None] = mapped_column(Text, default=None)
    options: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    asset_id: Mapped[str | None] = mapped_column(String(32), default=None)
    task_id: Mapped[str | None] = mapped_column(String(64), default=None)
    """Celery id of the task now queued or running for this job (for revoke)."""
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow,
                                                 index=True)
    updated_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    started_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True), default=None)
    """When a worker started the job's first stage."""
    finished_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True), default=None)
    lease_owner: Mapped[str | None] = mapped_column(String(128), default=None)
    """Who runs the stage at ``stage_index`` (one delivery of its task in one worker process);
    unset when no stage runs (`workers.leases`)."""
    lease_expires_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True),
                                                              default=None)
    """When the lease lapses unless its worker renews it; past it, the gateway queues the
    stage again."""
    lease_lapses: Mapped[int | None] = mapped_column(Integer, default=None)
    """Tries of the stage at ``stage_index`` whose worker stopped answering (lease lapsed);
    at ``stage_max_tries`` the job fails. Unset: none."""
    parent_id: Mapped[str | None] = mapped_column(String(32), default=None, index=True)
    """The sequence job this job reconstructs one frame of (`workers.sequence`); unset for a
    top-level job."""
    frame_index: Mapped[int | None] = mapped_column(Integer, default=None)
    """The capture frame a frame job reconstructs."""
    frame_counted: Mapped[bool | None] = mapped_column(Boolean, default=None)
    """Set once a frame job's end is counted in its parent (so it is counted once)."""
    frames_total: Mapped[int | None] = mapped_column(Integer, default=None)
    """A sequence job's frame count (its frames are jobs with ``parent_id`` = its id)."""
    frames_done: Mapped[int | None] = mapped_column(Integer, default=None)
    """A sequence job's frames that succeeded."""
    frames_failed: Mapped[int | None] = mapped_column(Integer, default=None)
    """A sequence job's frames that failed or were cancelled."""
    frame_errors: Mapped[dict[str, str] | None] = mapped_column(JSON, default=None)
    """A sequence job's failed frames: frame index (as text) -> why."""


class WorkerSeen(Base):
    """A live worker process: what it consumes and when it last said so (`workers.presence`)."""

    __tablename__ = "workers"

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    hostname: Mapped[str] = mapped_column(String(200))
    """The Celery node name (``name@host``)."""
    pid: Mapped[int] = mapped_column(Integer)
    queues: Mapped[list[str]] = mapped_column(JSON, default=list)
    started_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    last_seen: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow,
                                                index=True)


class Asset(Base):
    """The results of a succeeded job: ``files`` maps a name (mesh.glb) to its stored object."""

    __tablename__ = "assets"

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id"), unique=True)
    files: Mapped[dict[str, dict[str, Any]]] = mapped_column(JSON, default=dict)
    """name -> {"key": storage key, "sha256": hex, "bytes": int, "content_type": str}."""
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)


class Rig(Base):
    """Saved camera poses of a rig: uploaded as rig.json, or found by a calibration job."""

    __tablename__ = "rigs"

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    name: Mapped[str | None] = mapped_column(String(100), default=None, index=True)
    owner: Mapped[str | None] = mapped_column(String(120), default=None, index=True)
    """The owner of the key that uploaded it, or of the job that calibrated it."""
    cameras: Mapped[list[str]] = mapped_column(JSON, default=list)
    document: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    """The rig.json document: format, world_from_depth and the calibration's report."""
    source: Mapped[str] = mapped_column(String(16), default="upload")
    """upload (POST /rigs) | calibration (a job's calibrate stage; then id = the job's id)."""
    calibration_capture_id: Mapped[str | None] = mapped_column(String(32), default=None)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow,
                                                 index=True)


class Stream(Base):
    """A capture arriving frame-set by frame-set (docs/api.md, Streams); once closed, a worker
    assembles the stored frame-sets into one capture (`workers.streams`)."""

    __tablename__ = "streams"

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    owner: Mapped[str] = mapped_column(String(120), index=True)
    """``project:NAME`` for a key of a project, else ``key:ID`` (as a job's)."""
    name: Mapped[str | None] = mapped_column(String(100), default=None)
    state: Mapped[str] = mapped_column(String(16), default="receiving", index=True)
    """receiving | assembling (closed by the client, a worker builds the capture) | closed
    (``capture_id`` set) | failed (``error`` says why)."""
    fps: Mapped[float] = mapped_column(Float)
    depth_scale: Mapped[float] = mapped_column(Float)
    cameras: Mapped[list[dict[str, Any]]] = mapped_column(JSON, default=list)
    """The cameras as capture.json lists them, poses filled from ``rig_id``."""
    rig_id: Mapped[str | None] = mapped_column(String(32), default=None)
    frames_received: Mapped[int] = mapped_column(Integer, default=0)
    last_frame_index: Mapped[int | None] = mapped_column(Integer, default=None)
    """The highest frame index stored so far."""
    capture_id: Mapped[str | None] = mapped_column(String(32), default=None)
    error: Mapped[str | None] = mapped_column(Text, default=None)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow,
                                                 index=True)
    updated_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)


class StreamFrame(Base):
    """One stored frame-set of a stream. The primary key makes each index count once, across
    re-sends, gateway restarts and several gateways."""

    __tablename__ = "stream_frames"

    stream_id: Mapped[str] = mapped_column(ForeignKey("streams.id", ondelete="CASCADE"),
                                           primary_key=True)
    frame_index: Mapped[int] = mapped_column(Integer, primary_key=True)
    timestamp_us: Mapped[int] = mapped_column(BigInteger, default=0)
    """The device's timestamp of the frame-set, microseconds."""
    size_bytes: Mapped[int] = mapped_column(Integer)
    storage_key: Mapped[str] = mapped_column(String(200))
