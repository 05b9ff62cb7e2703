"""The training data of `volumesh train`: the mesh split, the depth pairs (made in worker
processes), and the twicing selector's and vertex gains' stages, which make their own data."""

from __future__ import annotations

import json
import time
from dataclasses import asdict
from pathlib import Path

import typer

VALIDATION_MESHES = ("spot", "fandisk")
TEST_MESH_PREFIX = "stanford-bunny"


def selector_stage(out: Path, train_set, val_set, config, seed: int) -> dict:
    """Trains the twicing selector on noisy draws of the training meshes, writes
    selector.safetensors; its report entry, with validation on the held-out meshes."""
    import numpy as np
    from tqdm import tqdm

    from pipeline.enhance.training import selector as st
    from pipeline.enhance.weights.loading import weights_to_bytes

    rng = np.random.default_rng(seed)
    t0 = time.monotonic()
    with tqdm(total=100, desc="selector data", unit="%") as data_bar:
        examples = st.selector_examples(train_set, config, rng,
                                        progress=lambda f: set_percent(data_bar, f))
    data_seconds = time.monotonic() - t0
    bar, cb = stage_bar("selector")
    model, log = st.train_selector(examples, config, seed, cb)
    bar.close()
    (out / "selector.safetensors").write_bytes(
        weights_to_bytes(model.state_dict(), asdict(config.model))
    )
    figures = st.validate_selector(model, val_set, config, np.random.default_rng(seed + 1000))
    typer.echo(f"selector: {json.dumps(figures)}")
    return {**log, "data_seconds": data_seconds, "draws": len(examples),
            "vertices": int(sum(len(e.features) for e in examples)), "validation": figures}


def gain_stage(out: Path, train_set, val_set, config, seed: int,
               weights: dict[str, bytes] | None) -> dict:
    """Trains a vertex gain network per method on noisy draws of the training meshes, enhanced
    by `weights` (None or a model left out: the shipped), writes <method>_gain.safetensors;
    its report entry, with validation on the held-out meshes."""
    import numpy as np
    from tqdm import tqdm

    from pipeline.enhance.training import gain as gt
    from pipeline.enhance.weights.loading import weights_to_bytes

    rng = np.random.default_rng(seed)
    t0 = time.monotonic()
    with tqdm(total=100, desc="gain data", unit="%") as data_bar:
        examples = gt.gain_examples(train_set, config, weights, rng,
                                    progress=lambda f: set_percent(data_bar, f))
    data_seconds = time.monotonic() - t0
    models, logs = {}, {}
    for method, method_examples in examples.items():
        bar, cb = stage_bar(f"{method} gain")
        models[method], logs[method] = gt.train_gain(method_examples, config, seed, cb)
        bar.close()
        (out / f"{method}_gain.safetensors").write_bytes(
            weights_to_bytes(models[method].state_dict(), asdict(config.model)))
    figures = gt.validate_gain(models, val_set, config, weights,
                               np.random.default_rng(seed + 1000))
    typer.echo(f"gain: {json.dumps(figures)}")
    first = next(iter(examples.values()))
    return {"config": asdict(config), "methods": logs, "data_seconds": data_seconds,
            "draws": len(first), "meshes": list(dict.fromkeys(e.name for e in first)),
            "vertices": int(sum(len(e.features) for e in first)), "validation": figures}


def network_weights(out: Path, init: Path | None) -> dict[str, bytes]:
    """The weights the gain stage enhances with: each model from this run's `out` when it
    trained it, else from `init`; models in neither are left to the shipped."""
    found = {}
    for name in ("selector", "regressor", "vae", "ldm"):
        for folder in (out, init):
            if folder is not None and (folder / f"{name}.safetensors").exists():
                found[name] = (folder / f"{name}.safetensors").read_bytes()
                break
    return found


POSES_PER_JOB = 8


def training_sets(meshes: Path, procedural: int, seed: int) -> tuple[list, list]:
    """(train, validation) lists of (name, mesh): the folder's meshes but the test model,
    split by mesh (VALIDATION_MESHES held apart), and `procedural` seeded shapes (one more
    held apart)."""
    import numpy as np

    from pipeline.enhance.training.data import procedural_meshes
    from pipeline.io.mesh_io import read_mesh

    sources = sorted(p for p in meshes.glob("*") if p.suffix.lower() in (".obj", ".ply", ".off"))
    sources = [p for p in sources if not p.stem.startswith(TEST_MESH_PREFIX)]
    named = [(p.stem, read_mesh(p)) for p in sources]
    val_names = [n for n, _ in named if n in VALIDATION_MESHES] or [n for n, _ in named][-1:]
    procs = procedural_meshes(np.random.default_rng(seed), procedural + 1)
    train_set = [(n, m) for n, m in named if n not in val_names] + procs[:-1]
    val_set = [(n, m) for n, m in named if n in val_names] + procs[-1:]
    return train_set, val_set


def training_pairs(items, data, seed: int, workers: int, progress=None):
    """`make_pairs` over jobs of at most POSES_PER_JOB poses of one mesh, each job with its
    own seed (and so its own remesh edge length), run by `workers` processes; the pairs do
    not depend on `workers`."""
    from concurrent.futures import ProcessPoolExecutor
    from dataclasses import replace
    from multiprocessing import get_context

    from pipeline.enhance.training.data import concat_pairs, make_pairs

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


def stage_bar(stage: str):
    """A progress bar for a training stage and the (fraction, text) callback that moves it."""
    from tqdm import tqdm

    bar = tqdm(total=1000, desc=stage)

    def cb(f: float, text: str) -> None:
        bar.n = int(f * 1000)
        bar.set_postfix_str(text, refresh=False)
        bar.refresh()

    return bar, cb


def set_percent(bar, fraction: float) -> None:
    """Moves a 0..100 % bar to `fraction`."""
    bar.n = int(fraction * 100)
    bar.refresh()
