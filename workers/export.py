"""A job's export stage: the mesh from the stage outputs, stored as the job's asset
(mesh.glb with Draco, mesh.ply, report.json); then the stage outputs are let go."""

from __future__ import annotations

import hashlib
import json
import logging
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from workers.artifacts import artifact_keys, discard_outputs, load_merged
from workers.context import WorkerContext
from workers.jobstore import JobView
from workers.plan import job_config

log = logging.getLogger(__name__)

_DRACO_OPTIONS = {"draco_position_bits": "position_quantization_bits",
                  "draco_normal_bits": "normal_quantization_bits",
                  "draco_color_bits": "color_quantization_bits",
                  "draco_compression_level": "compression_level"}
"""Job option -> `pipeline.io.gltf_io.DracoConfig` field."""


def _draco_config(options: dict[str, Any]) -> Any:
    from pipeline.io.gltf_io import DracoConfig

    return DracoConfig(**{_DRACO_OPTIONS[k]: v for k, v in options.items()
                          if k in _DRACO_OPTIONS})


def export(ctx: WorkerContext, job: JobView, stages: tuple[str, ...]) -> bool:
    """Build the mesh from the stage outputs; store mesh.glb (Draco), mesh.ply, report.json.
    True when this call marked the job succeeded."""
    from pipeline.io.gltf_io import encode_glb
    from pipeline.io.mesh_io import write_ply
    from pipeline.stages import mesh_from_artifacts, stage_stats

    started = time.perf_counter()
    found = ctx.store.capture(job.capture_id)
    if found is None:
        raise ValueError(f"capture {job.capture_id} no longer exists")
    sha256, _ = found
    config, config_digest = job_config(ctx, job)
    artifacts = load_merged(ctx, artifact_keys(sha256, stages, config))
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
    if not ctx.store.succeed(job.id, asset_id, files, seconds):
        return False
    _let_go(ctx, sha256, job.id)
    return True


def _let_go(ctx: WorkerContext, sha256: str, job_id: str) -> None:
    """Delete the capture's stage outputs now that the asset is stored (nothing retries an
    export of a succeeded job); a failure here costs disk, not the job."""
    try:
        removed = discard_outputs(ctx, sha256, job_id)
    except Exception:
        log.warning("job %s: could not delete its stage outputs", job_id, exc_info=True)
        return
    log.info("job %s: deleted %d stage outputs of capture %s", job_id, removed, sha256[:12])


def _report(ctx: WorkerContext, job: JobView, stages: tuple[str, ...], mesh: Any,
            stats: dict[str, Any], config_digest: str, glb_bytes: int,
            export_seconds: float) -> dict[str, Any]:
    """The same figures as ``volumesh reconstruct --report``, plus the job's."""
    from pipeline.stages import ENHANCE_STAGE
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
    """Store one asset file; its entry in the asset's ``files``."""
    key = f"assets/{asset_id}/{name}"
    ctx.storage.put_bytes(key, data)
    return {"key": key, "sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data),
            "content_type": content_type}
