"""Request and response bodies of the streams API (docs/api.md, Streams).

Cameras are checked here as the capture reader checks capture.json, so a stream that would
assemble into an unreadable capture is refused when it is created, not when it closes."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from app.core.poses import CAMERA_ID_PATTERN, Matrix4, check_rigid
from app.schemas import API_PREFIX, ID_PATTERN, _utc
from workers.models import Stream

StreamState = Literal["receiving", "assembling", "closed", "failed"]
MAX_STREAM_CAMERAS = 16
FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]


class Intrinsics(BaseModel):
    """A pinhole camera model in pixels, as capture.json holds it."""

    model_config = ConfigDict(extra="forbid")

    width: int = Field(ge=1, le=65535, description="Image width, pixels.")
    height: int = Field(ge=1, le=65535, description="Image height, pixels.")
    fx: float = Field(gt=0, allow_inf_nan=False, description="Focal length along x, pixels.")
    fy: float = Field(gt=0, allow_inf_nan=False, description="Focal length along y, pixels.")
    cx: float = Field(allow_inf_nan=False, description="Principal point x, pixels.")
    cy: float = Field(allow_inf_nan=False, description="Principal point y, pixels.")
    distortion: list[FiniteFloat] = Field(
        default_factory=list, max_length=8,
        description="OpenCV's coefficients [k1, k2, p1, p2, k3, k4, k5, k6], any prefix.")

    @property
    def pixels(self) -> int:
        return self.width * self.height


class StreamCamera(BaseModel):
    """One camera of a stream, exactly as capture.json lists it (docs/capture-format.md)."""

    model_config = ConfigDict(extra="forbid")

    id: str = Field(pattern=f"^{CAMERA_ID_PATTERN}$",
                    description="Camera id: the frame-set's folder name.")
    depth_intrinsics: Intrinsics = Field(description="The depth camera's model; every depth "
                                                     "PNG has exactly its size.")
    color_intrinsics: Intrinsics | None = Field(
        default=None, description="The colour camera's own model; null: colour is registered "
                                  "to depth (same size and model).")
    color_from_depth: Matrix4 | None = Field(
        default=None, description="4x4 rigid transform from depth to colour camera, metres; "
                                  "set exactly when color_intrinsics is.")
    world_from_depth: Matrix4 | None = Field(
        default=None, description="4x4 rigid transform: the depth camera's pose, metres; "
                                  "taken from the rig when the stream names one.")

    @model_validator(mode="after")
    def _consistent(self) -> StreamCamera:
        if (self.color_intrinsics is None) != (self.color_from_depth is None):
            raise ValueError(f"camera {self.id}: color_intrinsics and color_from_depth must "
                             "both be set or both null")
        for name in ("color_from_depth", "world_from_depth"):
            matrix = getattr(self, name)
            if matrix is not None:
                check_rigid(matrix, f"camera {self.id}: {name}")
        return self


class StreamCreate(BaseModel):
    """A stream of frame-sets from a rig of 1 to 16 cameras."""

    model_config = ConfigDict(extra="forbid")

    name: str | None = Field(default=None, min_length=1, max_length=100,
                             description="A name to tell the stream by.")
    fps: float = Field(gt=0, le=120, description="Frame-sets per second the rig captures.")
    depth_scale: float = Field(gt=0, allow_inf_nan=False,
                               description="Metres per depth unit (Azure Kinect: 0.001).")
    cameras: list[StreamCamera] = Field(min_length=1, max_length=MAX_STREAM_CAMERAS,
                                        description="The rig's cameras; ids unique.")
    rig_id: str | None = Field(default=None, pattern=ID_PATTERN,
                               description="A saved rig whose poses become the cameras' "
                                           "world_from_depth.")

    @model_validator(mode="after")
    def _unique_ids(self) -> StreamCreate:
        ids = [camera.id for camera in self.cameras]
        repeated = sorted({i for i in ids if ids.count(i) > 1})
        if repeated:
            raise ValueError(f"cameras: camera ids repeat: {', '.join(repeated)}")
        return self


class StreamPublic(BaseModel):
    id: str
    name: str | None
    state: StreamState = Field(description="receiving (takes frame-sets) | assembling (closed; "
                                            "a worker builds the capture) | closed | failed.")
    fps: float
    depth_scale: float
    cameras: list[StreamCamera] = Field(description="As stored, poses filled from the rig.")
    frames_received: int = Field(description="Frame-sets stored (each index counts once).")
    last_frame_index: int | None = Field(description="The highest frame index stored.")
    capture_id: str | None = Field(description="The assembled capture, once closed.")
    error: str | None = Field(description="Why the assembly failed.")
    created_at: datetime | None
    preview_url: str = Field(description="The WebSocket of the live preview.")

    @classmethod
    def of(cls, row: Stream) -> StreamPublic:
        return cls(id=row.id, name=row.name, state=row.state,  # type: ignore[arg-type]
                   fps=row.fps, depth_scale=row.depth_scale,
                   cameras=[StreamCamera.model_validate(c) for c in row.cameras or []],
                   frames_received=row.frames_received, last_frame_index=row.last_frame_index,
                   capture_id=row.capture_id, error=row.error, created_at=_utc(row.created_at),
                   preview_url=f"{API_PREFIX}/streams/{row.id}/preview")


class StreamPage(BaseModel):
    items: list[StreamPublic]
    total: int
    limit: int
    offset: int


class FrameSetPublic(BaseModel):
    """The acknowledgement of one frame-set: either way, the client may delete it."""

    stream_id: str
    index: int = Field(description="The frame index.")
    stored: bool = Field(description="True the first time the index arrived; false for a "
                                     "re-send (nothing changed).")
    frames_received: int = Field(description="Frame-sets the stream holds now.")
