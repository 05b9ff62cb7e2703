"""Request and response bodies of the REST API (docs/api.md)."""

from __future__ import annotations

from collections.abc import Callable
from datetime import UTC, datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from app.core.poses import Matrix4, check_poses
from app.core.stage_settings import check_settings, stage_settings
from workers.models import Asset, Capture, Job, Rig
from workers.presence import waiting_reason

API_PREFIX = "/api/v1"
ID_PATTERN = r"^[0-9a-f]{32}$"
RIG_FORMAT_ID: Literal["volumesh.rig/1"] = "volumesh.rig/1"
JobState = Literal["queued", "running", "succeeded", "failed", "cancelled"]
AssetFileName = Literal["mesh.glb", "mesh.ply", "report.json", "sequence.json"]


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
            "an unknown name or a value of the wrong kind is a 422 naming it; a worker checks "
            "the values' ranges, and the job fails with a message naming a bad one.")


class FrameRange(BaseModel):
    """Capture frames ``first`` to ``last``, both included (frame indices as capture.json
    lists them)."""

    model_config = ConfigDict(extra="forbid")

    first: int = Field(ge=0, description="The first frame index to reconstruct.")
    last: int = Field(ge=0, description="The last frame index to reconstruct (included).")

    @model_validator(mode="after")
    def _ordered(self) -> FrameRange:
        if self.last < self.first:
            raise ValueError(f"frames: last ({self.last}) comes before first ({self.first})")
        return self


class JobCreate(BaseModel):
    """A reconstruction of an uploaded capture; unset options take the pipeline's defaults.

    Camera poses come from the capture, or from one of: ``world_from_depth`` (inline),
    ``rig_id`` (a saved rig) or ``calibration_capture_id`` (calibrate first; the rig found is
    saved under the job's id). With ``calibration_capture_id`` and no ``capture_id`` the job
    only calibrates."""

    model_config = ConfigDict(extra="forbid")

    capture_id: str | None = Field(
        default=None, pattern=ID_PATTERN,
        description="Id returned by POST /captures; may be left out of a calibration-only job.")
    enhance: bool = Field(
        default=False, description="Run the enhancement stage (gpu queue; its method in "
        "`enhancement.method`). Off by default: it does not yet improve reconstructions "
        "(see the README).")
    target_edge_length_m: float | None = Field(
        default=None, gt=0.0005, le=0.5, description="Remeshing target edge length, metres.")
    voxel_size_m: float | None = Field(
        default=None, gt=0.0005, le=0.5, description="Voxel refinement cell size, metres.")
    frame_index: int | None = Field(
        default=None, ge=0, description="The capture frame to reconstruct (default: the first).")
    frames: Literal["all"] | FrameRange | None = Field(
        default=None, description="Reconstruct many frames as a sequence: \"all\" or "
        "{\"first\": F, \"last\": L}. Each frame runs as its own job (a frame job, listed "
        "with GET /jobs?parent_id=ID) in parallel; this job's asset is sequence.json, the "
        "viewer's manifest of the frames' meshes. A range outside the capture's frames is a "
        "422. Leave out to reconstruct one frame (`frame_index`).")
    world_from_depth: dict[str, list[list[float]]] | None = Field(
        default=None, max_length=64,
        description="Camera poses replacing the capture's (a rig.json's world_from_depth): "
                    "camera id -> 4x4 rigid transform, metres.")
    rig_id: str | None = Field(
        default=None, pattern=ID_PATTERN,
        description="A saved rig (POST /rigs, or a calibration job's id) whose poses replace "
                    "the capture's.")
    calibration_capture_id: str | None = Field(
        default=None, pattern=ID_PATTERN,
        description="A calibration capture (with a ChArUco target) to calibrate the rig from "
                    "first; the rig is saved as /rigs/{job id} for later captures.")
    rig_name: str | None = Field(default=None, min_length=1, max_length=100,
                                 description="Name to save the calibrated rig under.")
    calibration: StageSettings | None = Field(
        default=None, description="Calibration settings by field name (e.g. {\"icp\": true}).")
    depth_filter: StageSettings | None = Field(default=None, description=_SECTION)
    align: StageSettings | None = Field(default=None, description=_SECTION)
    registration: StageSettings | None = Field(default=None, description=_SECTION)
    crop: StageSettings | None = Field(default=None, description=_SECTION)
    voxel_refine: StageSettings | None = Field(default=None, description=_SECTION)
    meshing: StageSettings | None = Field(default=None, description=_SECTION)
    remesh: StageSettings | None = Field(default=None, description=_SECTION)
    surface_fit: StageSettings | None = Field(default=None, description=_SECTION)
    enhancement: dict[str, bool | int | float | str] | None = Field(
        default=None, description="Enhance stage settings by field name (method: regressor, "
        "ldm or classical; views; resolution; steps; strength; min_noise_ratio; "
        "self_check: keep the networks' update only where it beats the classical ending on a "
        "simulated copy).")
    colorize: StageSettings | None = Field(default=None, description=_SECTION)
    draco_position_bits: int | None = Field(
        default=None, ge=8, le=30, description="Draco position quantisation bits.")
    draco_normal_bits: int | None = Field(
        default=None, ge=4, le=30, description="Draco normal quantisation bits.")
    draco_color_bits: int | None = Field(
        default=None, ge=1, le=8, description="Draco colour quantisation bits (8: lossless).")
    draco_compression_level: int | None = Field(
        default=None, ge=0, le=10, description="Draco speed/size trade-off, 0..10.")

    _poses = field_validator("world_from_depth")(
        lambda v: check_poses(v, "world_from_depth"))

    @model_validator(mode="after")
    def _one_source_of_poses(self) -> JobCreate:
        given = [n for n in ("world_from_depth", "rig_id", "calibration_capture_id")
                 if getattr(self, n) is not None]
        if len(given) > 1:
            raise ValueError(f"give at most one of world_from_depth, rig_id and "
                             f"calibration_capture_id (got {', '.join(given)})")
        if self.capture_id is None and self.calibration_capture_id is None:
            raise ValueError("capture_id is required (or calibration_capture_id alone, "
                             "for a job that only calibrates)")
        if self.calibration_capture_id is None and (self.rig_name or self.calibration):
            raise ValueError("rig_name and calibration need calibration_capture_id")
        if self.frames is not None and (self.frame_index is not None
                                        or self.calibration_capture_id is not None):
            raise ValueError("frames reconstructs a sequence: give neither frame_index nor "
                             "calibration_capture_id with it (calibrate first, then use rig_id)")
        for section in stage_settings():
            values = getattr(self, section)
            if values is not None:
                check_settings(section, values)
        return self

    @property
    def calibrate_only(self) -> bool:
        return self.capture_id is None

    def options(self) -> dict[str, Any]:
        """The job's options (a sequence's frames take them too, with their frame_index)."""
        options = self.model_dump(exclude={"capture_id"}, exclude_none=True)
        if self.calibrate_only:
            options["calibrate_only"] = True
        return options


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
    waiting_reason: str | None = Field(
        default=None, description="Why the job waits, when no live worker consumes the queue "
        "its next stage waits on (e.g. no worker consumes the 'gpu' queue); else null.")
    parent_id: str | None = Field(
        default=None, description="The sequence job this job reconstructs one frame of.")
    frame_index: int | None = Field(
        default=None, description="The capture frame a frame job reconstructs.")
    frames_total: int | None = Field(
        default=None, description="A sequence job's frames (its frame jobs); null for others.")
    frames_done: int | None = Field(
        default=None, description="A sequence job's frames that succeeded.")
    frames_failed: int | None = Field(
        default=None, description="A sequence job's frames that failed (or were cancelled).")
    failed_frames: dict[str, str] | None = Field(
        default=None, description="A sequence job's failed frames: frame index -> why.")

    @classmethod
    def of(cls, row: Job | Any,
           consumed_queues: Callable[[], frozenset[str]] | None = None) -> JobPublic:
        """From an ORM row or a Core result row of the jobs table; with ``consumed_queues``
        (called only for a job that waits) it says why the job waits, if it waits in vain."""
        links = {"self": f"{API_PREFIX}/jobs/{row.id}",
                 "events": f"{API_PREFIX}/jobs/{row.id}/events",
                 "capture": f"{API_PREFIX}/captures/{row.capture_id}"}
        options = row.options or {}
        if options.get("rig_id"):
            links["rig"] = f"{API_PREFIX}/rigs/{options['rig_id']}"
        elif options.get("calibration_capture_id") and row.done_count > 0:
            links["rig"] = f"{API_PREFIX}/rigs/{row.id}"  # saved once calibrate (stage 0) is done
        _sequence_links(row, links)
        if row.asset_id and row.frames_total is not None:
            base = f"{API_PREFIX}/assets/{row.asset_id}"
            links.update({"asset": base, "sequence": f"{base}/sequence.json",
                          "viewer": f"/?sequence={base}/sequence.json"})
        elif row.asset_id:
            base = f"{API_PREFIX}/assets/{row.asset_id}"
            links.update({"asset": base, "mesh_glb": f"{base}/mesh.glb",
                          "mesh_ply": f"{base}/mesh.ply", "report": f"{base}/report.json"})
        return cls(id=row.id, capture_id=row.capture_id, state=row.state,  # type: ignore[arg-type]
                   stage=row.stage, progress=row.progress, stages=list(row.stages or []),
                   stage_timings=dict(row.stage_timings or {}), error=row.error,
                   asset_id=row.asset_id, options=dict(row.options or {}),
                   created_at=_utc(row.created_at), updated_at=_utc(row.updated_at),
                   started_at=_utc(row.started_at), finished_at=_utc(row.finished_at),
                   links=links, waiting_reason=None if consumed_queues is None else
                   waiting_reason(row, consumed_queues),
                   parent_id=row.parent_id, frame_index=row.frame_index,
                   frames_total=row.frames_total, frames_done=row.frames_done,
                   frames_failed=row.frames_failed, failed_frames=row.frame_errors)


def _sequence_links(row: Job | Any, links: dict[str, str]) -> None:
    """A frame job links its sequence; a sequence job lists its frame jobs."""
    if row.parent_id:
        links["parent"] = f"{API_PREFIX}/jobs/{row.parent_id}"
    if row.frames_total is not None:
        links["frames"] = f"{API_PREFIX}/jobs?parent_id={row.id}"


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
    def of(cls, row: Asset, share: str | None = None) -> AssetPublic:
        """The asset; read through a share link, its file URLs carry the same ``share``."""
        query = "" if share is None else f"?share={share}"
        files = {name: AssetFile(url=f"{API_PREFIX}/assets/{row.id}/{name}{query}",
                                 bytes=f["bytes"], sha256=f["sha256"],
                                 content_type=f["content_type"])
                 for name, f in (row.files or {}).items()}
        return cls(id=row.id, job_id=row.job_id, files=files, created_at=_utc(row.created_at))


SHARE_MAX_S = 30 * 24 * 3600


class AssetShareCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")

    expires_in_s: int = Field(default=7 * 24 * 3600, ge=60, le=SHARE_MAX_S,
                              description="How long the link works, seconds (1 minute to 30 "
                                          "days; default 7 days).")


class AssetSharePublic(BaseModel):
    asset_id: str
    share: str = Field(description="The token: add `?share=TOKEN` to the asset's URLs to read "
                                   "them with no API key.")
    expires_at: datetime
    viewer_url: str = Field(description="The viewer showing the asset, for anyone with the link.")
    files: dict[str, str] = Field(description="File name -> its URL with the token.")


class RigCreate(BaseModel):
    """A rig file (what ``volumesh calibrate`` writes): poses plus any report fields."""

    model_config = ConfigDict(extra="allow")

    format: Literal["volumesh.rig/1"] = RIG_FORMAT_ID
    name: str | None = Field(default=None, min_length=1, max_length=100,
                             description="A name to find the rig by (e.g. the studio).")
    world_from_depth: dict[str, Matrix4] = Field(
        min_length=1, max_length=64,
        description="Camera id -> 4x4 rigid transform from its depth frame to the world, metres.")

    _poses = field_validator("world_from_depth")(
        lambda v: check_poses(v, "world_from_depth"))

    def document(self) -> dict[str, Any]:
        """The rig.json document to store (the name is kept apart)."""
        return self.model_dump(exclude={"name"})


class RigPublic(BaseModel):
    id: str
    name: str | None
    cameras: list[str]
    source: Literal["upload", "calibration"] = Field(
        description="upload (POST /rigs) or calibration (the calibrate stage of job `id`).")
    calibration_capture_id: str | None
    world_from_depth: dict[str, Matrix4]
    report: dict[str, Any] = Field(
        description="The calibration's quality report (reprojection RMS per camera, "
                    "triangulation error, views used, warnings) when there is one.")
    created_at: datetime | None
    links: dict[str, str]

    @classmethod
    def of(cls, row: Rig) -> RigPublic:
        document = dict(row.document or {})
        poses = document.pop("world_from_depth", {})
        document.pop("format", None)
        base = f"{API_PREFIX}/rigs/{row.id}"
        return cls(id=row.id, name=row.name, cameras=list(row.cameras or []),
                   source=row.source,  # type: ignore[arg-type]
                   calibration_capture_id=row.calibration_capture_id, world_from_depth=poses,
                   report=document, created_at=_utc(row.created_at),
                   links={"self": base, "rig_json": f"{base}/rig.json"})


class RigPage(BaseModel):
    items: list[RigPublic]
    total: int
    limit: int
    offset: int


class Health(BaseModel):
    status: Literal["ok", "unavailable"]
    checks: dict[str, str] = Field(default_factory=dict)


class Problem(BaseModel):
    """RFC 9457 problem details (``application/problem+json``), the body of every error."""

    model_config = ConfigDict(extra="allow", title="Problem")

    type: str = Field(description="A URI whose last segment names the kind of problem "
                                  "(not-found, validation-error, ...).")
    title: str = Field(description="The HTTP status's phrase.")
    status: int = Field(ge=400, le=599, description="The HTTP status code.")
    detail: str = Field(description="What went wrong and what to do about it.")
    instance: str | None = Field(default=None, description="The path that was requested.")
    errors: list[dict[str, Any]] | None = Field(
        default=None, description="validation-error only: each error's `loc`, `msg` and "
                                  "`type`.")
