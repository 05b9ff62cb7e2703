"""A job's plan: the stages it runs, the config they read, and one key per stage over the
settings that stage and the ones before it read (the key its stored output is found by)."""

from __future__ import annotations

import dataclasses
import hashlib
import json
from typing import Any

from workers.context import WorkerContext
from workers.jobstore import JobView

EXPORT_STAGE = "export"
"""The job's last stage: the mesh from the stage outputs, stored as the job's asset."""
CALIBRATE_STAGE = "calibrate"
"""The job's first stage when it calibrates: the rig's poses from a calibration capture."""


def plan_stages(options: dict[str, Any]) -> list[str]:
    """The stages a job with these options runs: calibrate first when asked, export last."""
    from pipeline.stages import ENHANCE_STAGE, STAGES

    first = [CALIBRATE_STAGE] if options.get("calibration_capture_id") else []
    if options.get("calibrate_only"):
        return first
    stages = [s for s in STAGES if options.get("enhance", False) or s != ENHANCE_STAGE]
    return [*first, *stages, EXPORT_STAGE]


def work_stages(stages: tuple[str, ...]) -> tuple[str, ...]:
    """The stages that pass array artifacts along (neither calibrate nor export)."""
    return tuple(s for s in stages if s not in (CALIBRATE_STAGE, EXPORT_STAGE))


def stage_keys(stages: tuple[str, ...], config: Any) -> list[str]:
    """One key per stage over every setting that stage or an earlier one reads, so changing a
    late stage's settings reuses the early stages' stored outputs while they are kept (until
    an asset of the capture is stored and no other job of it is live)."""
    from pipeline.stages import SECTION_FIRST_STAGE

    whole = dataclasses.asdict(config)
    position = {stage: i for i, stage in enumerate(stages)}
    first_reader = {name: position.get(SECTION_FIRST_STAGE[name], len(stages))
                    for name in whole if name in SECTION_FIRST_STAGE}
    keys = []
    for index, stage in enumerate(stages):
        seen = {name: value for name, value in whole.items()
                if first_reader.get(name, 0) <= index}
        text = json.dumps([index, stage, seen], sort_keys=True, default=str)
        keys.append(hashlib.sha256(text.encode()).hexdigest()[:24])
    return keys


def job_config(ctx: WorkerContext, job: JobView) -> tuple[Any, str]:
    """The job's reconstruction config and its hash; poses from the job's own calibration
    when it calibrates first."""
    from pipeline.stage_config import config_from_options, config_hash, reconstruction_options

    options = reconstruction_options(job.options)
    if job.options.get("calibration_capture_id"):
        rig = ctx.store.rig(job.id)
        if rig is None:
            raise ValueError(f"job {job.id}: its calibrate stage saved no rig")
        options["world_from_depth"] = rig["world_from_depth"]
    config = config_from_options(options)
    return config, config_hash(config)
