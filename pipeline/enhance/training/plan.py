"""What a training run works on: its configuration with the command line's edits, its stages,
the split of the source meshes and the depth pairs (made in worker processes)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Protocol

import numpy as np

from pipeline.enhance.training import config as tc
from pipeline.enhance.training.data import (
    MIXES,
    NOISE_KINDS,
    DataConfig,
    DepthPairs,
    concat_pairs,
    make_pairs,
    procedural_meshes,
    with_mix,
)
from pipeline.geometry.mesh import TriangleMesh

STAGES = ("selector", "regressor", "vae", "ldm", "finetune", "gain")
"""Every stage of a run, in the order they run."""
NETWORK_STAGES = ("regressor", "vae", "ldm", "finetune")
"""The stages that train on depth pairs."""
DEPTH_NETWORKS = ("regressor", "vae", "ldm")
"""The weights files of the depth networks."""
VALIDATION_MESHES = ("spot", "fandisk")
"""Source meshes held apart for validation (the last one where none of these is there)."""
TEST_MESH_PREFIX = "stanford-bunny"
"""Source meshes never trained on: the benchmark's test model."""
POSES_PER_JOB = 8
"""Poses of one mesh a worker process renders at a time."""

NamedMeshes = list[tuple[str, TriangleMesh]]


class WeightsStore(Protocol):
    """A folder of a run's files by name (weights, checkpoints, report): the CLI gives its
    --out and --init folders as these, so that the run itself reads and writes no files."""

    where: str
    """The folder, for messages."""

    def names(self) -> list[str]:
        """The files at the folder's top, sorted."""
        ...

    def has(self, name: str) -> bool: ...

    def read(self, name: str) -> bytes: ...

    def write(self, name: str, data: bytes) -> None:
        """Writes `name` whole or not at all (an interrupted write spoils no checkpoint)."""
        ...


def run_config(config: str, budget_scale: float = 1.0, poses: int | None = None,
               mix: str = "full", minutes: float | None = None, lr: float | None = None,
               loss_mask: float | None = None, noise: str | None = None) -> tc.TrainConfig:
    """The named configuration with the command line's edits; ValueError names a bad option.

    `noise`: the comma-separated noise models every stage's noisy meshes draw from (None:
    the config's, all of `NOISE_KINDS`)."""
    if config not in tc.CONFIGS:
        raise ValueError(f"--config: {config!r} is not one of {', '.join(tc.CONFIGS)}")
    if mix not in MIXES:
        raise ValueError(f"--mix: {mix!r} is not one of {', '.join(MIXES)}")
    cfg = tc.CONFIGS[config]
    if budget_scale != 1.0:
        cfg = tc.scaled(cfg, budget_scale)
    if poses is not None:
        cfg = replace(cfg, data=replace(cfg.data, poses_per_mesh=poses))
    cfg = replace(cfg, data=with_mix(cfg.data, mix))
    if minutes is not None:
        cfg = tc.capped(cfg, minutes)
    if lr is not None:
        cfg = tc.with_lr(cfg, lr)
    if loss_mask is not None:
        cfg = replace(cfg, loss_mask_threshold_n=loss_mask)
    if noise is not None:
        cfg = with_noise_kinds(cfg, noise)
    return cfg


def with_noise_kinds(cfg: tc.TrainConfig, noise: str) -> tc.TrainConfig:
    """`cfg` with every stage's noise models set to the comma-separated `noise`."""
    names = {k.strip() for k in noise.split(",") if k.strip()}
    if not names or not names <= set(NOISE_KINDS):
        raise ValueError(f"--noise: {noise!r} is not a comma-separated list of "
                         f"{', '.join(NOISE_KINDS)}")
    kinds = tuple(k for k in NOISE_KINDS if k in names)
    return replace(cfg, data=replace(cfg.data, noise_kinds=kinds),
                   selector=replace(cfg.selector, noise_kinds=kinds),
                   gain=replace(cfg.gain, noise_kinds=kinds))


def wanted_stages(stages: str, init: WeightsStore | None) -> list[str]:
    """The comma-separated stages, checked against each other and against the --init weights
    (None: none given)."""
    wanted = [s.strip() for s in stages.split(",") if s.strip()]
    for s in wanted:
        if s not in STAGES:
            raise ValueError(f"--stages: unknown stage {s!r}")
    if init is not None:
        missing = [n for n in DEPTH_NETWORKS if not init.has(f"{n}.safetensors")]
        if missing:
            raise ValueError(f"--init: {init.where} has no {', '.join(missing)}.safetensors")
        if {"vae", "ldm"} & set(wanted):
            raise ValueError("--init: leave out the vae and ldm stages (finetune starts from "
                             "the folder's)")
    return wanted


def training_sets(named: NamedMeshes, procedural: int, seed: int
                  ) -> tuple[NamedMeshes, NamedMeshes]:
    """(train, validation) lists of (name, mesh): the named meshes but the test model, split
    by mesh (`VALIDATION_MESHES` held apart), and `procedural` seeded shapes (one more held
    apart)."""
    named = [(n, m) for n, m in named if not n.startswith(TEST_MESH_PREFIX)]
    val_names = [n for n, _ in named if n in VALIDATION_MESHES] or [n for n, _ in named][-1:]
    procs = procedural_meshes(np.random.default_rng(seed), procedural + 1)
    train_set = [(n, m) for n, m in named if n not in val_names] + procs[:-1]
    val_set = [(n, m) for n, m in named if n in val_names] + procs[-1:]
    return train_set, val_set


def training_pairs(items: NamedMeshes, data: DataConfig, seed: int, workers: int,
                   progress: Callable[[float], None] | None = None) -> DepthPairs:
    """`make_pairs` over jobs of at most `POSES_PER_JOB` poses of one mesh, each job with its
    own seed (and so its own remesh edge length), run by `workers` processes; the pairs do
    not depend on `workers`."""
    from concurrent.futures import ProcessPoolExecutor
    from multiprocessing import get_context

    sources, configs = [], []
    for name, mesh in items:
        for start in range(0, data.poses_per_mesh, POSES_PER_JOB):
            sources.append([(name, mesh)])
            configs.append(replace(data, poses_per_mesh=min(POSES_PER_JOB,
                                                            data.poses_per_mesh - start)))
    seeds = [seed * 100_003 + k for k in range(len(sources))]
    parts = []
    # spawn, not fork: the parent may already hold CUDA or torch's thread pools.
    with ProcessPoolExecutor(workers, mp_context=get_context("spawn")) as pool:
        done = (pool.map(make_pairs, sources, configs, seeds) if workers > 1
                else map(make_pairs, sources, configs, seeds))
        for part in done:
            parts.append(part)
            if progress is not None:
                progress(len(parts) / len(sources))
    return concat_pairs(parts)
