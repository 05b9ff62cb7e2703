"""The work stages' outputs in storage: ``.npz`` files keyed by the capture's hash, the
stage's position and name, and the stage's key over the settings it depends on.

They live while a job of their capture may read them: a finished job's export removes its
capture's outputs once no other job of that capture is queued or running (those may share
them by key), so storage keeps assets, not tens of megabytes of intermediates per job."""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from sqlalchemy import func, select

from workers.context import WorkerContext
from workers.jobstore import LIVE
from workers.models import Capture, Job
from workers.plan import stage_keys, work_stages
from workers.storage import ARTIFACTS


def artifact_key(sha256: str, index: int, stage: str, chain: str) -> str:
    """The storage key of one work stage's output."""
    return f"{ARTIFACTS}/{sha256}/{index:02d}-{stage}-{chain}.npz"


def artifact_keys(sha256: str, stages: tuple[str, ...], config: Any) -> list[str]:
    """Storage keys of the work stages' outputs, in order."""
    work = work_stages(stages)
    return [artifact_key(sha256, i, stage, key)
            for i, (stage, key) in enumerate(zip(work, stage_keys(work, config), strict=True))]


def save_npz(ctx: WorkerContext, key: str, arrays: dict[str, np.ndarray]) -> None:
    """Store the arrays under ``key`` (written to a local file first, then moved)."""
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


def load_npz(ctx: WorkerContext, key: str) -> dict[str, np.ndarray]:
    """The arrays stored under ``key`` (through a cached copy when storage is remote)."""
    local = ctx.storage.local_path(key)
    if local is None:
        local = _cached_copy(ctx, key)
        if not local.is_file():
            ctx.storage.get_to_path(key, local)
    with np.load(local, allow_pickle=False) as data:
        return {name: data[name] for name in data.files}


def load_merged(ctx: WorkerContext, keys: list[str]) -> dict[str, np.ndarray]:
    """The outputs under ``keys`` merged in order (later keys win), as stages read them."""
    merged: dict[str, np.ndarray] = {}
    for key in keys:
        merged.update(load_npz(ctx, key))
    return merged


def _cached_copy(ctx: WorkerContext, key: str) -> Path:
    """Where a worker keeps its copy of a remote output (one flat folder; `/` -> `_`)."""
    return ctx.settings.cache_dir / ARTIFACTS / key.replace("/", "_")


def capture_in_use(ctx: WorkerContext, sha256: str, finished_job_id: str) -> bool:
    """Whether a job other than ``finished_job_id`` on the capture ``sha256`` is queued or
    running (it may load the capture's stored outputs, shared by key)."""
    with ctx.store.sessions() as session:
        count = session.scalar(
            select(func.count()).select_from(Job).join(Capture, Job.capture_id == Capture.id)
            .where(Capture.sha256 == sha256, Job.state.in_(LIVE), Job.id != finished_job_id))
    return bool(count)


def discard_outputs(ctx: WorkerContext, sha256: str, finished_job_id: str) -> int:
    """Delete the capture's stage outputs (stored and cached copies) unless another job of it
    is live; returns how many stored ones went. Called once the finished job's asset is kept.

    A job created in the instant between the check and the delete may find an output gone;
    its stage then fails and retries, which is the price of not tracking readers per key."""
    if capture_in_use(ctx, sha256, finished_job_id):
        return 0
    prefix = f"{ARTIFACTS}/{sha256}/"
    removed = ctx.storage.delete_prefix(prefix)
    cached = _cached_copy(ctx, prefix)
    for copy in cached.parent.glob(f"{cached.name}*"):
        copy.unlink(missing_ok=True)
    return removed
