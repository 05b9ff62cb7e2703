"""The work behind the thin tasks: validate a capture, run one stage of a job, export a job.

A job may calibrate first (``calibration_capture_id``): its ``calibrate`` stage saves the rig
under the job's id, and the later stages read their camera poses from it.

A job runs as a chain of stage tasks. Each stage's output is stored as ``.npz`` keyed by the
capture's hash, the stage and a hash of the settings of that stage and of the stages before
it, so a re-run (a retry, a redelivery after a worker died, a second job with the same or
later-only changes) loads it instead of computing it again. A task queues its successor before
it records the stage done; a duplicate delivery then finds the stage counted and stops, so a
job neither stalls nor forks.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from workers.celery_app import TASK_STAGE, queue_for_stage
from workers.db import init_db, make_engine, make_sessionmaker
from workers.jobstore import JobStore, JobView
from workers.settings import Settings
from workers.storage import Storage, make_storage

if TYPE_CHECKING:
    from pipeline.enhance.config import EnhanceConfig
    from pipeline.enhance.networks import EnhanceNetworks

log = logging.getLogger(__name__)

EXPORT_STAGE = "export"
ENHANCE_STAGE = "enhance"
CALIBRATE_STAGE = "calibrate"
_NOT_PIPELINE = ("rig_id", "calibration_capture_id", "rig_name", "calibration",
                 "calibrate_only")
"""Job options the service acts on itself; the rest configure the reconstruction."""


class JobCancelledError(Exception):
    """The job was cancelled while one of its stages ran."""


@dataclass
class WorkerContext:
    """What a worker process holds open: settings, job store, storage, and the enhance
    stage's networks between jobs."""

    settings: Settings
    store: JobStore
    storage: Storage
    networks: EnhanceNetworks | None = None
    """The networks of the last enhance stage this process ran (`enhance_networks`)."""

    @classmethod
    def create(cls, settings: Settings) -> WorkerContext:
        engine = make_engine(settings)
        init_db(engine)
        return cls(settings, JobStore(make_sessionmaker(engine)), make_storage(settings))

    def enhance_networks(self, config: EnhanceConfig) -> EnhanceNetworks:
        """The networks `config` runs: those kept from the last enhance stage where they
        fit it, else loaded now and kept in their place (one set at a time, so a worker
        holds one LDM: the old set is let go before the new one loads). A method that runs
        no network leaves the kept set as it is."""
        from pipeline.enhance.networks import load_networks, uses_networks

        if not uses_networks(config):
            return load_networks(config)
        if self.networks is None or not self.networks.fits(config):
            started = time.perf_counter()
            self.networks = None
            self.networks = load_networks(config)
            log.info("enhance networks for %s on %s loaded in %.2f s", config.method,
                     self.networks.key[1], time.perf_counter() - started)
        return self.networks


SendTask = Callable[[str, list[Any], str], str]
"""send(task name, args, queue) -> task id."""


def capture_path(ctx: WorkerContext, sha256: str, key: str) -> Path:
    """A local path of the stored capture zip (a cached copy when storage is remote)."""
    local = ctx.storage.local_path(key)
    if local is not None:
        return local
    cached = ctx.settings.cache_dir / "captures" / f"{sha256}.zip"
    if not cached.is_file():
        ctx.storage.get_to_path(key, cached)
    return cached


def validate_capture(ctx: WorkerContext, capture_id: str) -> None:
    """Read the whole capture (every image decoded); mark it ready or rejected with why."""
    from pipeline.io.capture_io import open_capture

    found = ctx.store.capture(capture_id)
    if found is None:
        return  # the upload was abandoned meanwhile
    sha256, key = found
    try:
        with open_capture(capture_path(ctx, sha256, key)) as reader:
            for frame in reader.meta.frame_indices:
                reader.read_frame(frame)
            cameras, frames = len(reader.meta.cameras), len(reader.meta.frames)
    except ValueError as exc:
        ctx.store.capture_rejected(capture_id, str(exc))
        return
    ctx.store.capture_validated(capture_id, cameras, frames)


def plan_stages(options: dict[str, Any]) -> list[str]:
    """The stages a job with these options runs: calibrate first when asked, export last."""
    from pipeline.stages import STAGES

    first = [CALIBRATE_STAGE] if options.get("calibration_capture_id") else []
    if options.get("calibrate_only"):
        return first
    stages = [s for s in STAGES if options.get("enhance", False) or s != ENHANCE_STAGE]
    return [*first, *stages, EXPORT_STAGE]


def _artifact_key(sha256: str, index: int, stage: str, chain: str) -> str:
    return f"artifacts/{sha256}/{index:02d}-{stage}-{chain}.npz"


SECTION_FIRST_STAGE = {"depth_filter": "filter", "align": "align", "registration": "register",
                       "crop": "register", "voxel_refine": "refine", "meshing": "mesh",
                       "remesh": "remesh", "enhance": "enhance", "enhancement": "enhance",
                       "colorize": "colorize"}
"""The first stage that reads each config field. A field missing here counts as read by every
stage (reuse is then lost, never wrong); one whose reader is not planned, by none."""


def stage_keys(stages: tuple[str, ...], config: Any) -> list[str]:
    """One key per stage over every setting that stage or an earlier one reads, so changing a
    late stage's settings reuses the early stages' stored outputs."""
    import dataclasses

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


def _save_npz(ctx: WorkerContext, key: str, arrays: dict[str, np.ndarray]) -> None:
    folder = ctx.settings.cache_dir / "tmp"
    folder.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=folder, suffix=".npz")
    try:
        with os.fdopen(fd, "wb") as out:
            savez: Any = np.savez  # numpy's stub mistakes array names for its keywords
            savez(out, **arrays)
        ctx.storage.put_file(key, Path(tmp), move=True)
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)


def _load_npz(ctx: WorkerContext, key: str) -> dict[str, np.ndarray]:
    local = ctx.storage.local_path(key)
    if local is None:
        local = ctx.settings.cache_dir / "artifacts" / key.replace("/", "_")
        if not local.is_file():
            ctx.storage.get_to_path(key, local)
    with np.load(local, allow_pickle=False) as data:
        return {name: data[name] for name in data.files}


class _Progress:
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


def _job_config(ctx: WorkerContext, job: JobView) -> tuple[Any, str]:
    from pipeline.stage_config import config_from_options, config_hash

    options = _pipeline_options(job.options)
    if job.options.get("calibration_capture_id"):
        rig = ctx.store.rig(job.id)
        if rig is None:
            raise ValueError(f"job {job.id}: its calibrate stage saved no rig")
        options["world_from_depth"] = rig["world_from_depth"]
    config = config_from_options(options)
    return config, config_hash(config)


def _work_stages(stages: tuple[str, ...]) -> tuple[str, ...]:
    """The stages that pass array artifacts along (neither calibrate nor export)."""
    return tuple(s for s in stages if s not in (CALIBRATE_STAGE, EXPORT_STAGE))


def _artifact_keys(sha256: str, stages: tuple[str, ...], config: Any) -> list[str]:
    """Storage keys of the work stages' outputs, in order."""
    work = _work_stages(stages)
    return [_artifact_key(sha256, i, stage, key)
            for i, (stage, key) in enumerate(zip(work, stage_keys(work, config), strict=True))]


def _pipeline_options(options: dict[str, Any]) -> dict[str, Any]:
    # Export settings (Draco) and where poses come from are the service's, not the pipeline's.
    return {k: v for k, v in options.items()
            if not k.startswith("draco_") and k not in _NOT_PIPELINE}


def calibrate(ctx: WorkerContext, job: JobView, index: int, count: int) -> bool:
    """Calibrate from the job's calibration capture and save the rig under the job's id;
    False when a redelivered task finds it saved already."""
    from pipeline.calibration import CalibrationConfig
    from pipeline.calibration import calibrate as find_poses
    from pipeline.io.capture_io import open_capture
    from pipeline.io.rig_io import rig_to_json
    from pipeline.stage_config import replace_section

    if ctx.store.rig(job.id) is not None:
        return False
    capture_id = job.options["calibration_capture_id"]
    found = ctx.store.capture(capture_id)
    if found is None:
        raise ValueError(f"calibration capture {capture_id} no longer exists")
    config = replace_section(CalibrationConfig(), job.options.get("calibration", {}),
                             "calibration")
    progress = _Progress(ctx, job.id, index, count)
    with open_capture(capture_path(ctx, *found)) as reader:
        world_from_depth, report = find_poses(reader, config, progress=progress)
    ctx.store.save_rig(job.id, rig_to_json(world_from_depth, report),
                       job.options.get("rig_name"), capture_id)
    return True


def _run_stage(ctx: WorkerContext, job: JobView, stages: tuple[str, ...], index: int) -> bool:
    """Compute and store the stage's output; False when it was already stored."""
    from pipeline.io.capture_io import open_capture
    from pipeline.stages import run_stage

    found = ctx.store.capture(job.capture_id)
    if found is None:
        raise ValueError(f"capture {job.capture_id} no longer exists")
    sha256, capture_key = found
    config, _ = _job_config(ctx, job)
    keys = _artifact_keys(sha256, stages, config)
    position = _work_stages(stages).index(stages[index])
    out_key = keys[position]
    if ctx.storage.exists(out_key):
        return False
    inputs: dict[str, np.ndarray] = {}
    for earlier in keys[:position]:
        inputs.update(_load_npz(ctx, earlier))
    progress = _Progress(ctx, job.id, index, len(stages))
    networks = (partial(ctx.enhance_networks, config.enhancement)
                if stages[index] == ENHANCE_STAGE else None)
    with open_capture(capture_path(ctx, sha256, capture_key)) as reader:
        outputs = run_stage(stages[index], reader, inputs, config, progress=progress,
                            networks=networks)
    _save_npz(ctx, out_key, outputs)
    return True


def _draco_config(options: dict[str, Any]) -> Any:
    from pipeline.io.gltf_io import DracoConfig

    fields = {"draco_position_bits": "position_quantization_bits",
              "draco_normal_bits": "normal_quantization_bits",
              "draco_color_bits": "color_quantization_bits",
              "draco_compression_level": "compression_level"}
    return DracoConfig(**{fields[k]: v for k, v in options.items() if k in fields})


def export(ctx: WorkerContext, job: JobView, stages: tuple[str, ...]) -> None:
    """Build the mesh from the stage outputs; store mesh.glb (Draco), mesh.ply, report.json."""
    from pipeline.io.gltf_io import encode_glb
    from pipeline.io.mesh_io import write_ply
    from pipeline.stages import mesh_from_artifacts, stage_stats

    started = time.perf_counter()
    found = ctx.store.capture(job.capture_id)
    if found is None:
        raise ValueError(f"capture {job.capture_id} no longer exists")
    sha256, _ = found
    config, config_digest = _job_config(ctx, job)
    artifacts: dict[str, np.ndarray] = {}
    for key in _artifact_keys(sha256, stages, config):
        artifacts.update(_load_npz(ctx, key))
    mesh = mesh_from_artifacts(artifacts)
    glb = encode_glb(mesh, draco=_draco_config(job.options),
                     extras={"volumesh": {"job_id": job.id, "capture_id": job.capture_id}})
    asset_id = job.id  # one asset per job: a redelivered export rewrites the same files
    files = {"mesh.glb": _put(ctx, asset_id, "mesh.glb", glb, "model/gltf-binary")}
    folder = ctx.settings.cache_dir / "tmp"
    folder.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=folder) as tmp:
        ply_path = Path(tmp) / "mesh.ply"
        write_ply(ply_path, mesh)
        files["mesh.ply"] = _put(ctx, asset_id, "mesh.ply", ply_path.read_bytes(),
                                 "application/octet-stream")
    seconds = time.perf_counter() - started
    report = _report(ctx, job, stages, mesh, stage_stats(artifacts), config_digest,
                     len(glb), seconds)
    files["report.json"] = _put(ctx, asset_id, "report.json",
                                json.dumps(report, indent=1).encode(), "application/json")
    ctx.store.succeed(job.id, asset_id, files, seconds)


def _report(ctx: WorkerContext, job: JobView, stages: tuple[str, ...], mesh: Any,
            stats: dict[str, Any], config_digest: str, glb_bytes: int,
            export_seconds: float) -> dict[str, Any]:
    """The same figures as ``volumesh reconstruct --report``, plus the job's."""
    from workers.models import Job

    with ctx.store.sessions() as session:
        row = session.get(Job, job.id)
        seconds = dict(row.stage_timings or {}) if row else {}
    seconds["export"] = round(export_seconds, 4)
    vertices = np.asarray(mesh.vertices_m)
    return {
        "job_id": job.id,
        "capture_id": job.capture_id,
        "options": job.options,
        "rig_id": job.options.get("rig_id") or (
            job.id if job.options.get("calibration_capture_id") else None),
        "rig": _rig_summary(ctx, job),
        "stages": list(stages),
        "stage_seconds": seconds,
        "total_seconds": round(sum(seconds.values()), 3),
        "points": stats.get("register", {}).get("points"),
        "refined_points": stats.get("refine", {}).get("points"),
        "samples": stats.get("mesh", {}).get("samples"),
        "vertices": int(mesh.vertex_count),
        "triangles": int(mesh.face_count),
        "has_colors": mesh.vertex_colors is not None,
        "bounds_m": [vertices.min(axis=0).round(5).tolist(),
                     vertices.max(axis=0).round(5).tolist()] if len(vertices) else None,
        "enhance": {"requested": bool(job.options.get("enhance", True)),
                    "applied": ENHANCE_STAGE in stages},
        "stage_stats": stats,
        "config_hash": config_digest,
        "glb_bytes": glb_bytes,
    }


def _rig_summary(ctx: WorkerContext, job: JobView) -> dict[str, Any] | None:
    """The calibrated rig's poses and headline figures (the viewer draws its frusta)."""
    if not job.options.get("calibration_capture_id"):
        return None
    rig = ctx.store.rig(job.id) or {}
    keep = ("world_from_depth", "reprojection_rms_px", "triangulation_error_mm", "warnings")
    return {k: rig[k] for k in keep if k in rig}


def _put(ctx: WorkerContext, asset_id: str, name: str, data: bytes,
         content_type: str) -> dict[str, Any]:
    key = f"assets/{asset_id}/{name}"
    ctx.storage.put_bytes(key, data)
    return {"key": key, "sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data),
            "content_type": content_type}
