"""The work stages' outputs in storage: ``.npz`` files keyed by the capture's hash, the
stage's position and name, and the stage's key over the settings it depends on."""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from workers.context import WorkerContext
from workers.plan import stage_keys, work_stages


def artifact_key(sha256: str, index: int, stage: str, chain: str) -> str:
    """The storage key of one work stage's output."""
    return f"artifacts/{sha256}/{index:02d}-{stage}-{chain}.npz"


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
        local = ctx.settings.cache_dir / "artifacts" / key.replace("/", "_")
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
