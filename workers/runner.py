"""Running one stage of a job: the work behind the ``volumesh.stage`` task.

A job may calibrate first (``calibration_capture_id``): its ``calibrate`` stage saves the rig
under the job's id, and the later stages read their camera poses from it.

A job runs as a chain of stage tasks. Each stage's output is stored (`workers.artifacts`)
under a key over the capture and the settings of that stage and of the stages before it, so
a re-run (a retry, a redelivery after a worker died, a second job with the same or
later-only changes) loads it instead of computing it again. A task queues its successor before
it records the stage done; a duplicate delivery then finds the stage counted and stops, so a
job neither stalls nor forks.

A stage runs under a lease (`workers.leases`) that a heartbeat thread renews: a delivery finding
the lease held by another does not start, and a stage whose worker died is queued again by the
gateway once its lease lapses.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from functools import partial
from typing import Any

from workers.artifacts import artifact_keys, load_merged, save_npz
from workers.captures import capture_limits, capture_path
from workers.celery_app import TASK_STAGE, queue_for_stage
from workers.context import WorkerContext
from workers.export import export
from workers.jobstore import JobView
from workers.leases import Heartbeat, new_owner
from workers.plan import CALIBRATE_STAGE, EXPORT_STAGE, job_config, plan_stages, work_stages
from workers.sequence import frame_over

log = logging.getLogger(__name__)

SendTask = Callable[[str, list[Any], str], str]
"""send(task name, args, queue) -> task id."""


class JobCancelledError(Exception):
    """The job was cancelled while one of its stages ran."""


class LeaseLostError(Exception):
    """The stage's lease went to another delivery (this worker was taken for dead)."""


class StageProgress:
    """Throttled progress writes that also notice a cancellation or a lost lease."""

    def __init__(self, ctx: WorkerContext, job_id: str, index: int, count: int,
                 lease: Heartbeat | None = None) -> None:
        self.ctx, self.job_id, self.index, self.count = ctx, job_id, index, count
        self.lease = lease
        self.last = 0.0

    def __call__(self, fraction: float) -> None:
        if self.lease is not None and self.lease.lost.is_set():
            raise LeaseLostError(self.job_id)
        now = time.monotonic()
        if now - self.last < self.ctx.settings.progress_interval_s:
            return
        self.last = now
        state = self.ctx.store.progress(self.job_id, (self.index + fraction) / self.count)
        if state != "running":
            raise JobCancelledError(self.job_id)


def stage_name(ctx: WorkerContext, job_id: str, index: int) -> str:
    """The name of stage ``index`` of the job, for messages ("stage 3" when unknown)."""
    job = ctx.store.load(job_id)
    if job is not None and 0 <= index < len(job.stages):
        return job.stages[index]
    return f"stage {index}"


def run_step(ctx: WorkerContext, job_id: str, index: int, task_id: str | None,
             send: SendTask) -> None:
    """Run stage ``index`` of the job (or skip it when a duplicate), then queue the next."""
    job = ctx.store.load(job_id)
    if job is not None and job.parent_id and job.state not in ("queued", "running"):
        frame_over(ctx.store.sessions, job_id, send)  # counted once; a retry counts a lost one
    if job is None or job.state not in ("queued", "running") or job.done_count > index:
        return
    if job.frames_total is not None:
        return  # a sequence runs no stages itself: its frame jobs do (workers.sequence)
    stages = job.stages or ctx.store.set_plan(job_id, plan_stages(job.options))
    if index >= len(stages):
        return
    name = stages[index]
    owner, lease_s = new_owner(), ctx.settings.stage_lease_s
    if not ctx.store.start_stage(job_id, index, name, task_id, owner, lease_s):
        log.info("job %s stage %d (%s) not started: done, job over, or held by another "
                 "delivery", job_id, index, name)
        return
    log.info("job %s stage %d (%s) starting", job_id, index, name)
    with Heartbeat(ctx.store.sessions, job_id, owner, lease_s) as lease:
        try:
            _run_leased(ctx, job, stages, index, send, lease)
        except LeaseLostError:
            log.warning("job %s stage %d (%s): its lease went to another delivery; stopped",
                        job_id, index, name)


def _run_leased(ctx: WorkerContext, job: JobView, stages: tuple[str, ...], index: int,
                send: SendTask, lease: Heartbeat) -> None:
    """Run the stage whose lease this delivery holds, then queue the next."""
    job_id, name = job.id, stages[index]
    if name == EXPORT_STAGE:
        if export(ctx, job, stages):
            frame_over(ctx.store.sessions, job_id, send)
        return
    started = time.perf_counter()
    if name == CALIBRATE_STAGE:
        computed = calibrate(ctx, job, index, len(stages), lease)
    else:
        computed = _run_stage(ctx, job, stages, index, lease)
    seconds = time.perf_counter() - started if computed else 0.0  # 0: output reused
    if lease.lost.is_set():
        raise LeaseLostError(job_id)  # the new holder queues the next stage
    if ctx.store.state(job_id) != "running":
        return  # cancelled while the stage ran
    if index + 1 == len(stages):  # a job that only calibrates ends here, with no asset
        ctx.store.complete(job_id, {name: seconds})
        return
    send(TASK_STAGE, [job_id, index + 1], queue_for_stage(stages[index + 1]))
    ctx.store.finish_stage(job_id, index, name, seconds, (index + 1) / len(stages))


def calibrate(ctx: WorkerContext, job: JobView, index: int, count: int,
              lease: Heartbeat | None = None) -> bool:
    """Calibrate from the job's calibration capture and save the rig under the job's id;
    False when a redelivered task finds it saved already."""
    from pipeline.calibration import CalibrationConfig
    from pipeline.calibration import calibrate as find_poses
    from pipeline.io.capture_io import open_capture
    from pipeline.io.rig_io import rig_to_json
    from pipeline.stage_config import CALIBRATION_SECTION, replace_section

    if ctx.store.rig(job.id) is not None:
        return False
    capture_id = job.options["calibration_capture_id"]
    found = ctx.store.capture(capture_id)
    if found is None:
        raise ValueError(f"calibration capture {capture_id} no longer exists")
    config = replace_section(CalibrationConfig(), job.options.get(CALIBRATION_SECTION, {}),
                             CALIBRATION_SECTION)
    progress = StageProgress(ctx, job.id, index, count, lease)
    with open_capture(capture_path(ctx, *found), capture_limits(ctx.settings)) as reader:
        world_from_depth, report = find_poses(reader, config, progress=progress)
    ctx.store.save_rig(job.id, rig_to_json(world_from_depth, report),
                       job.options.get("rig_name"), capture_id)
    log.info("job %s stage %d (%s) stored output", job.id, index, CALIBRATE_STAGE)
    return True


def _run_stage(ctx: WorkerContext, job: JobView, stages: tuple[str, ...], index: int,
               lease: Heartbeat | None = None) -> bool:
    """Compute and store the stage's output; False when it was already stored."""
    from pipeline.io.capture_io import open_capture
    from pipeline.stages import ENHANCE_STAGE, run_stage

    found = ctx.store.capture(job.capture_id)
    if found is None:
        raise ValueError(f"capture {job.capture_id} no longer exists")
    sha256, capture_key = found
    config, _ = job_config(ctx, job)
    keys = artifact_keys(sha256, stages, config)
    position = work_stages(stages).index(stages[index])
    out_key = keys[position]
    if ctx.storage.exists(out_key):
        return False
    inputs = load_merged(ctx, keys[:position])
    progress = StageProgress(ctx, job.id, index, len(stages), lease)
    networks = (partial(ctx.enhance_networks, config.enhancement)
                if stages[index] == ENHANCE_STAGE else None)
    limits = capture_limits(ctx.settings)
    with open_capture(capture_path(ctx, sha256, capture_key), limits) as reader:
        outputs = run_stage(stages[index], reader, inputs, config, progress=progress,
                            networks=networks)
    save_npz(ctx, out_key, outputs)
    log.info("job %s stage %d (%s) stored output", job.id, index, stages[index])
    return True
