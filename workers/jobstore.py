"""What workers write to the job store: stage starts, progress, finishes, failures, results.

Every update is conditional on the job's state, so a duplicate or late task (a redelivery after
a worker died, a task of a cancelled job) changes nothing.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import timedelta
from typing import Any

from sqlalchemy import CursorResult, case, update
from sqlalchemy.orm import Session, sessionmaker

from workers.leases import lease_free, new_owner
from workers.models import Asset, Capture, Job, Rig, utcnow
from workers.sequence import mark_running

LIVE = ("queued", "running")


@dataclass(frozen=True)
class JobView:
    """A detached copy of the job fields a stage task needs."""

    id: str
    capture_id: str
    state: str
    stages: tuple[str, ...]
    done_count: int
    options: dict[str, Any]
    asset_id: str | None
    parent_id: str | None = None
    """The sequence job this job is one frame of (`workers.sequence`)."""
    frames_total: int | None = None
    """Set on a sequence job: it runs frame jobs, not stages of its own."""


class JobStore:
    def __init__(self, sessions: sessionmaker[Session]) -> None:
        self.sessions = sessions

    def load(self, job_id: str) -> JobView | None:
        with self.sessions() as session:
            job = session.get(Job, job_id)
            if job is None:
                return None
            return JobView(id=job.id, capture_id=job.capture_id, state=job.state,
                           stages=tuple(job.stages or ()), done_count=job.done_count,
                           options=dict(job.options or {}), asset_id=job.asset_id,
                           parent_id=job.parent_id, frames_total=job.frames_total)

    def capture(self, capture_id: str) -> tuple[str, str] | None:
        """(sha256, storage key) of a capture, or None."""
        with self.sessions() as session:
            row = session.get(Capture, capture_id)
            return None if row is None else (row.sha256, row.storage_key)

    def set_plan(self, job_id: str, stages: list[str]) -> tuple[str, ...]:
        """Fix the job's stages once (the first task decides); returns the stages in force."""
        with self.sessions.begin() as session:
            job = session.get(Job, job_id, with_for_update=True)
            if job is None:
                return ()
            if not job.stages:
                job.stages = stages
            return tuple(job.stages)

    def start_stage(self, job_id: str, index: int, name: str, task_id: str | None,
                    owner: str | None = None, lease_s: float = 30.0) -> bool:
        """Mark the stage running under ``owner``'s lease for ``lease_s`` (`workers.leases`);
        False when the job is over, the stage already done, or another delivery holds its
        lease (live, or lapsed and left to the gateway's sweep)."""
        now = utcnow()
        owner = owner or new_owner()
        with self.sessions.begin() as session:
            result: CursorResult[Any] = session.execute(  # type: ignore[assignment]
                update(Job)
                .where(Job.id == job_id, Job.state.in_(LIVE), Job.done_count <= index,
                       lease_free(index, owner))
                .values(state="running", stage=name, stage_index=index, task_id=task_id,
                        updated_at=now, lease_owner=owner,
                        lease_expires_at=now + timedelta(seconds=lease_s),
                        # lapses count per stage: a new stage starts with none
                        lease_lapses=case((Job.stage_index == index, Job.lease_lapses),
                                          else_=None)))
            if result.rowcount:
                session.execute(update(Job).where(Job.id == job_id, Job.started_at.is_(None))
                                .values(started_at=now))
                mark_running(session, job_id)
            return bool(result.rowcount)

    def progress(self, job_id: str, progress: float) -> str | None:
        """Record overall progress 0..1; returns the job's state (None: job gone)."""
        with self.sessions.begin() as session:
            session.execute(update(Job).where(Job.id == job_id, Job.state.in_(LIVE))
                            .values(progress=min(max(progress, 0.0), 1.0), updated_at=utcnow()))
            job = session.get(Job, job_id)
            return None if job is None else job.state

    def state(self, job_id: str) -> str | None:
        with self.sessions() as session:
            job = session.get(Job, job_id)
            return None if job is None else job.state

    def finish_stage(self, job_id: str, index: int, name: str, seconds: float,
                     progress: float) -> bool:
        """Count the stage done; True for the one task that advanced it (it queued the next)."""
        with self.sessions.begin() as session:
            job = session.get(Job, job_id, with_for_update=True)
            if job is None or job.state not in LIVE or job.done_count != index:
                return False
            job.done_count = index + 1
            job.stage_timings = {**(job.stage_timings or {}), name: round(seconds, 4)}
            job.progress = progress
            job.updated_at = utcnow()
            return True

    def succeed(self, job_id: str, asset_id: str, files: dict[str, dict[str, Any]],
                export_seconds: float) -> bool:
        """Store the job's asset and mark it succeeded; True for the call that did."""
        with self.sessions.begin() as session:
            job = session.get(Job, job_id, with_for_update=True)
            if job is None or job.state not in LIVE:
                return False
            if session.get(Asset, asset_id) is None:
                session.add(Asset(id=asset_id, job_id=job_id, files=files))
            now = utcnow()
            job.state = "succeeded"
            job.asset_id = asset_id
            job.progress = 1.0
            job.done_count = len(job.stages or ())
            job.stage_timings = {**(job.stage_timings or {}), "export": round(export_seconds, 4)}
            job.updated_at = now
            job.finished_at = now
            return True

    def complete(self, job_id: str, seconds_by_stage: dict[str, float]) -> bool:
        """Mark a job that makes no asset (it only calibrates) succeeded."""
        with self.sessions.begin() as session:
            job = session.get(Job, job_id, with_for_update=True)
            if job is None or job.state not in LIVE:
                return False
            now = utcnow()
            job.state, job.progress, job.updated_at, job.finished_at = "succeeded", 1.0, now, now
            job.done_count = len(job.stages or ())
            job.stage_timings = {**(job.stage_timings or {}),
                                 **{k: round(v, 4) for k, v in seconds_by_stage.items()}}
            return True

    def rig(self, rig_id: str) -> dict[str, Any] | None:
        """The rig.json document of a saved rig, or None."""
        with self.sessions() as session:
            row = session.get(Rig, rig_id)
            return None if row is None else dict(row.document)

    def save_rig(self, rig_id: str, document: dict[str, Any], name: str | None,
                 calibration_capture_id: str) -> None:
        """Save (or, on a redelivery, overwrite) the rig a calibration found."""
        with self.sessions.begin() as session:
            row = session.get(Rig, rig_id) or Rig(id=rig_id)
            job = session.get(Job, rig_id)  # the calibrating job: its owner owns the rig
            row.owner = None if job is None else job.owner
            row.name, row.document, row.source = name, document, "calibration"
            row.cameras = sorted(document["world_from_depth"])
            row.calibration_capture_id = calibration_capture_id
            session.add(row)

    def fail(self, job_id: str, error: str) -> bool:
        """Mark a live job failed with why; True for the call that did."""
        now = utcnow()
        with self.sessions.begin() as session:
            result: CursorResult[Any] = session.execute(  # type: ignore[assignment]
                update(Job).where(Job.id == job_id, Job.state.in_(LIVE))
                .values(state="failed", error=error[:4000], updated_at=now, finished_at=now))
            return bool(result.rowcount)

    def capture_validated(self, capture_id: str, cameras: int,
                          frame_indices: tuple[int, ...]) -> None:
        with self.sessions.begin() as session:
            row = session.get(Capture, capture_id)
            if row is not None and row.state == "validating":
                row.state, row.cameras, row.error = "ready", cameras, None
                row.frames, row.frame_indices = len(frame_indices), list(frame_indices)

    def capture_rejected(self, capture_id: str, error: str) -> None:
        with self.sessions.begin() as session:
            row = session.get(Capture, capture_id)
            if row is not None and row.state == "validating":
                row.state, row.error = "rejected", error[:4000]
