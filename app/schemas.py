"""Request and response bodies of the REST API (the contract in DESIGN.md)."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from workers.models import Asset, Capture, Job

API_PREFIX = "/api/v1"
ID_PATTERN = r"^[0-9a-f]{32}$"
JobState = Literal["queued", "running", "succeeded", "failed", "cancelled"]
AssetFileName = Literal["mesh.glb", "mesh.ply", "report.json"]


def _utc(value: datetime | None) -> datetime | None:
    # SQLite hands back naive datetimes; they were written in UTC.
    if value is not None and value.tzinfo is None:
        return value.replace(tzinfo=UTC)
    return value


class CapturePublic(BaseModel):
    id: str = Field(description="Capture id (the start of its content's SHA-256).")
    cameras: int | None = Field(description="Cameras in the capture.")
    frames: int | None = Field(description="Frames per camera.")
    bytes: int = Field(description="Size of the stored zip.")
    sha256: str
    state: Literal["validating", "ready", "rejected"]
    created_at: datetime | None

    @classmethod
    def of(cls, row: Capture) -> CapturePublic:
        return cls(id=row.id, cameras=row.cameras, frames=row.frames, bytes=row.size_bytes,
                   sha256=row.sha256, state=row.state,  # type: ignore[arg-type]
                   created_at=_utc(row.created_at))


StageSettings = dict[str, bool | int | float | list[float]]
_SECTION = ("Settings of one pipeline stage by field name (e.g. meshing: {\"poisson_depth\": 7}); "
            "a worker checks them, and the job fails with a message naming a bad one.")


class JobCreate(BaseModel):
    """A reconstruction of an uploaded capture; unset options take the pipeline's defaults."""

    model_config = ConfigDict(extra="forbid")

    capture_id: str = Field(pattern=ID_PATTERN, description="Id returned by POST /captures.")
    enhance: bool = Field(default=True, description="Run the LDM enhancement stage (gpu queue).")
    target_edge_length_m: float | None = Field(
        default=None, gt=0.0005, le=0.5, description="Remeshing target edge length, metres.")
    voxel_size_m: float | None = Field(
        default=None, gt=0.0005, le=0.5, description="Voxel refinement cell size, metres.")
    frame_index: int | None = Field(
        default=None, ge=0, description="The capture frame to reconstruct (default: the first).")
    world_from_depth: dict[str, list[list[float]]] | None = Field(
        default=None, max_length=64,
        description="Camera poses replacing the capture's (a rig.json's world_from_depth): "
                    "camera id -> 4x4 rigid transform, metres.")
    depth_filter: StageSettings | None = Field(default=None, description=_SECTION)
    align: StageSettings | None = Field(default=None, description=_SECTION)
    registration: StageSettings | None = Field(default=None, description=_SECTION)
    crop: StageSettings | None = Field(default=None, description=_SECTION)
    voxel_refine: StageSettings | None = Field(default=None, description=_SECTION)
    meshing: StageSettings | None = Field(default=None, description=_SECTION)
    remesh: StageSettings | None = Field(default=None, description=_SECTION)
    colorize: StageSettings | None = Field(default=None, description=_SECTION)
    draco_position_bits: int | None = Field(
        default=None, ge=8, le=30, description="Draco position quantisation bits.")
    draco_normal_bits: int | None = Field(
        default=None, ge=4, le=30, description="Draco normal quantisation bits.")
    draco_color_bits: int | None = Field(
        default=None, ge=1, le=8, description="Draco colour quantisation bits (8: lossless).")
    draco_compression_level: int | None = Field(
        default=None, ge=0, le=10, description="Draco speed/size trade-off, 0..10.")

    def options(self) -> dict[str, Any]:
        return self.model_dump(exclude={"capture_id"}, exclude_none=True)


class JobPublic(BaseModel):
    id: str
    capture_id: str
    state: JobState
    stage: str | None = Field(description="The stage now running (or the last one run).")
    progress: float = Field(ge=0, le=1, description="Fraction of the job done, 0..1.")
    stages: list[str] = Field(description="The job's stages in order (set once it starts).")
    stage_timings: dict[str, float] = Field(
        description="Seconds each finished stage took; 0 when its stored output was reused.")
    error: str | None
    asset_id: str | None
    options: dict[str, Any]
    created_at: datetime | None
    updated_at: datetime | None
    started_at: datetime | None = Field(description="When a worker started the first stage.")
    finished_at: datetime | None
    links: dict[str, str] = Field(description="URLs of this job, its events and its results.")

    @classmethod
    def of(cls, row: Job | Any) -> JobPublic:
        """From an ORM row or a Core result row of the jobs table."""
        links = {"self": f"{API_PREFIX}/jobs/{row.id}",
                 "events": f"{API_PREFIX}/jobs/{row.id}/events",
                 "capture": f"{API_PREFIX}/captures/{row.capture_id}"}
        if row.asset_id:
            base = f"{API_PREFIX}/assets/{row.asset_id}"
            links.update({"asset": base, "mesh_glb": f"{base}/mesh.glb",
                          "mesh_ply": f"{base}/mesh.ply", "report": f"{base}/report.json"})
        return cls(id=row.id, capture_id=row.capture_id, state=row.state,  # type: ignore[arg-type]
                   stage=row.stage, progress=row.progress, stages=list(row.stages or []),
                   stage_timings=dict(row.stage_timings or {}), error=row.error,
                   asset_id=row.asset_id, options=dict(row.options or {}),
                   created_at=_utc(row.created_at), updated_at=_utc(row.updated_at),
                   started_at=_utc(row.started_at), finished_at=_utc(row.finished_at),
                   links=links)


class JobPage(BaseModel):
    items: list[JobPublic]
    total: int
    limit: int
    offset: int


class CapturePage(BaseModel):
    items: list[CapturePublic]
    total: int
    limit: int
    offset: int


class AssetFile(BaseModel):
    url: str
    bytes: int
    sha256: str
    content_type: str


class AssetPublic(BaseModel):
    id: str
    job_id: str
    files: dict[str, AssetFile]
    created_at: datetime | None

    @classmethod
    def of(cls, row: Asset) -> AssetPublic:
        files = {name: AssetFile(url=f"{API_PREFIX}/assets/{row.id}/{name}", bytes=f["bytes"],
                                 sha256=f["sha256"], content_type=f["content_type"])
                 for name, f in (row.files or {}).items()}
        return cls(id=row.id, job_id=row.job_id, files=files, created_at=_utc(row.created_at))


class Health(BaseModel):
    status: Literal["ok", "unavailable"]
    checks: dict[str, str] = Field(default_factory=dict)


class Problem(BaseModel):
    """RFC 9457 problem details, the body of every error."""

    type: str
    title: str
    status: int
    detail: str
    instance: str | None = None
