"""Running one stage of a job: the work behind the ``volumesh.stage`` task.

A job may calibrate first (``calibration_capture_id``): its ``calibrate`` stage saves the rig
under the job's id, and the later stages read their camera poses from it.

A job runs as a chain of stage tasks. Each stage's output is stored (`workers.artifacts`)
under a key over the capture and the settings of that stage and of the stages before it, so
a re-run (a retry, a redelivery after a worker died, a second job with the same or
later-only changes) loads it instead of computing it again. A task queues its successor before
it records the stage done; a duplicate delivery then finds the stage counted and stops, so a
job neither stalls nor forks.
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
from workers.plan import CALIBRATE_STAGE, EXPORT_STAGE, job_config, plan_stages, work_stages

log = logging.getLogger(__name__)

SendTask = Callable[[str, list[Any], str], str]
"""send(task name, args, queue) -> task id."""


class JobCancelledError(Exception):
    """The job was cancelled while one of its stages ran."""


class StageProgress:
    """Throttled progress writes that also notice a cancellation."""

    def __init__(self, ctx: WorkerContext, job_id: str, index: int, count: int) -> None:
        self.ctx, self.job_id, self.index, self.count = ctx, job_id, index, count
        self.last = 0.0

    def __call__(self, fraction: float) -> None:
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
    if job is None or job.state not in ("queued", "running") or job.done_count > index:
        return
    stages = job.stages or ctx.store.set_plan(job_id, plan_stages(job.options))
    if index >= len(stages):
        return
    name = stages[index]
    if not ctx.store.start_stage(job_id, index, name, task_id):
        return
    log.info("job %s stage %d (%s) starting", job_id, index, name)
    if name == EXPORT_STAGE:
        export(ctx, job, stages)
        return
    started = time.perf_counter()
    if name == CALIBRATE_STAGE:
        computed = calibrate(ctx, job, index, len(stages))
    else:
        computed = _run_stage(ctx, job, stages, index)
    seconds = time.perf_counter() - started if computed else 0.0  # 0: output reused
    if ctx.store.state(job_id) != "running":
        return  # cancelled while the stage ran
    if index + 1 == len(stages):  # a job that only calibrates ends here, with no asset
        ctx.store.complete(job_id, {name: seconds})
        return
    send(TASK_STAGE, [job_id, index + 1], queue_for_stage(stages[index + 1]))
    ctx.store.finish_stage(job_id, index, name, seconds, (index + 1) / len(stages))


def calibrate(ctx: WorkerContext, job: JobView, index: int, count: int) -> bool:
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
    progress = StageProgress(ctx, job.id, index, count)
    with open_capture(capture_path(ctx, *found), capture_limits(ctx.settings)) as reader:
        world_from_depth, report = find_poses(reader, config, progress=progress)
    ctx.store.save_rig(job.id, rig_to_json(world_from_depth, report),
                       job.options.get("rig_name"), capture_id)
    return True


def _run_stage(ctx: WorkerContext, job: JobView, stages: tuple[str, ...], index: int) -> bool:
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
    progress = StageProgress(ctx, job.id, index, len(stages))
    networks = (partial(ctx.enhance_networks, config.enhancement)
                if stages[index] == ENHANCE_STAGE else None)
    limits = capture_limits(ctx.settings)
    with open_capture(capture_path(ctx, sha256, capture_key), limits) as reader:
        outputs = run_stage(stages[index], reader, inputs, config, progress=progress,
                            networks=networks)
    save_npz(ctx, out_key, outputs)
    return True
