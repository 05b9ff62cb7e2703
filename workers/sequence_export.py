"""A sequence job's export: the manifest of its frames' meshes (`workers.sequence`), written
as the sequence's asset once every frame is over."""

from __future__ import annotations

import hashlib
import json
import logging
import statistics
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from workers.context import WorkerContext
from workers.models import Job
from workers.sequence import LIVE

log = logging.getLogger(__name__)

DEFAULT_FPS = 30.0
"""Playback rate of a capture whose frames carry no distinct timestamps."""


@dataclass(frozen=True)
class FrameOutcome:
    """One frame job of a sequence as its export sees it."""

    job_id: str
    frame_index: int
    state: str
    asset_id: str | None
    error: str | None


def frame_outcomes(sessions: sessionmaker[Session], parent_id: str) -> list[FrameOutcome]:
    with sessions() as session:
        rows = session.execute(select(Job.id, Job.frame_index, Job.state, Job.asset_id, Job.error)
                               .where(Job.parent_id == parent_id).order_by(Job.frame_index))
        return [FrameOutcome(r.id, r.frame_index or 0, r.state, r.asset_id, r.error)
                for r in rows]


def fps_from_timestamps(timestamps_us: Sequence[int]) -> float:
    """Frames per second from the frames' timestamps (their median step); `DEFAULT_FPS` when
    they give none."""
    steps = [b - a for a, b in zip(timestamps_us, timestamps_us[1:], strict=False) if b > a]
    if not steps:
        return DEFAULT_FPS
    return round(min(240.0, 1e6 / statistics.median(steps)), 3)


def union_bounds(boxes: Sequence[tuple[list[float], list[float]]]
                 ) -> dict[str, list[float]]:
    """The box holding every (min, max) box, metres."""
    return {"min": [min(b[0][axis] for b in boxes) for axis in range(3)],
            "max": [max(b[1][axis] for b in boxes) for axis in range(3)]}


def build_manifest(fps: float, frames: list[FrameOutcome],
                   reports: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """The sequence manifest (app.web.SequenceManifest) of the succeeded frames, in frame
    order; GLB links relative to the manifest (``../{asset id}/mesh.glb``), so one served at
    ``/api/v1/assets/{id}/sequence.json`` finds its frames next to it."""
    played = [f for f in frames if f.state == "succeeded" and f.asset_id]
    boxes = [(reports[f.job_id]["bounds_m"][0], reports[f.job_id]["bounds_m"][1])
             for f in played if reports.get(f.job_id, {}).get("bounds_m")]
    bounds = union_bounds(boxes) if boxes else {"min": [0.0] * 3, "max": [0.0] * 3}
    return {
        "version": 1,
        "fps": fps,
        "bounds": bounds,
        "frames": [{"url": f"../{f.asset_id}/mesh.glb", "frame_index": f.frame_index,
                    "job_id": f.job_id, "asset_id": f.asset_id,
                    "triangles": reports.get(f.job_id, {}).get("triangles")} for f in played],
        "failed_frames": [{"frame_index": f.frame_index, "job_id": f.job_id,
                           "error": f.error or f.state} for f in frames
                          if f.state != "succeeded"],
    }


def export_sequence(ctx: WorkerContext, parent_id: str) -> None:
    """Write the sequence's manifest as its asset once every frame is over (idempotent: a
    redelivery rewrites the same files); fail it when every frame failed."""
    started = time.perf_counter()
    with ctx.store.sessions() as session:
        parent = session.get(Job, parent_id)
        if parent is None or parent.state not in LIVE or not parent.frames_total:
            return
        if (parent.frames_done or 0) + (parent.frames_failed or 0) < parent.frames_total:
            return
        capture_id = parent.capture_id
    frames = frame_outcomes(ctx.store.sessions, parent_id)
    if not any(f.state == "succeeded" and f.asset_id for f in frames):
        why = "; ".join(f"frame {f.frame_index}: {f.error or f.state}" for f in frames)
        ctx.store.fail(parent_id, f"every frame failed: {why}")
        return
    reports = {f.job_id: _frame_report(ctx, f.asset_id) for f in frames
               if f.state == "succeeded" and f.asset_id}
    fps = fps_from_timestamps(_timestamps_us(ctx, capture_id, [f.frame_index for f in frames]))
    data = json.dumps(build_manifest(fps, frames, reports), indent=1).encode()
    key = f"assets/{parent_id}/sequence.json"
    ctx.storage.put_bytes(key, data)
    files = {"sequence.json": {"key": key, "sha256": hashlib.sha256(data).hexdigest(),
                               "bytes": len(data), "content_type": "application/json"}}
    ctx.store.succeed(parent_id, parent_id, files, time.perf_counter() - started)


def _frame_report(ctx: WorkerContext, asset_id: str | None) -> dict[str, Any]:
    key = f"assets/{asset_id}/report.json"
    try:
        data = b"".join(ctx.storage.iter_range(key, 0, ctx.storage.size(key) - 1))
        return dict(json.loads(data))
    except (OSError, ValueError):
        log.warning("asset %s: its report.json could not be read", asset_id, exc_info=True)
        return {}


def _timestamps_us(ctx: WorkerContext, capture_id: str, frame_indices: list[int]) -> list[int]:
    """The capture's timestamps of these frames, in frame order."""
    from pipeline.io.capture_io import open_capture
    from workers.captures import capture_limits, capture_path

    found = ctx.store.capture(capture_id)
    if found is None:
        return []
    wanted = set(frame_indices)
    with open_capture(capture_path(ctx, *found), capture_limits(ctx.settings)) as reader:
        return [f.timestamp_us for f in sorted(reader.meta.frames, key=lambda f: f.index)
                if f.index in wanted]
