"""A whole training run: the twicing selector (the pre-smoothing), the depth networks on pairs
pre-smoothed by it, then the vertex gains of the mesh update, each stage's weights and report
entry written to the run's `WeightsStore` as it ends, with training.json, the run's record."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from pipeline.enhance.training.config import TrainConfig
from pipeline.enhance.training.gain import GainTrainConfig
from pipeline.enhance.training.plan import (
    DEPTH_NETWORKS,
    NETWORK_STAGES,
    NamedMeshes,
    WeightsStore,
    training_pairs,
    training_sets,
)
from pipeline.enhance.training.runner import StageBar, StageRunner
from pipeline.enhance.training.selector import SelectorTrainConfig

REPORT = "training.json"
"""The run's record: its config, data and each stage's figures."""


@dataclass(frozen=True)
class RunSettings:
    """What a run trains, on what, and where."""

    cfg: TrainConfig
    stages: list[str]
    """`plan.wanted_stages`."""
    seed: int
    device: Any
    """A torch.device."""
    resume: bool
    """Continue a run in the same store: finished stages are kept, checkpoints resumed."""
    workers: int
    """Processes making the depth pairs."""
    procedural: int
    """Procedural shapes beside the source meshes."""


def train_run(settings: RunSettings, meshes: NamedMeshes, out: WeightsStore,
              init: WeightsStore | None, bar: StageBar,
              told: Callable[[str, dict], None] = lambda stage, figures: None) -> dict:
    """Runs `settings.stages` on the source `meshes` (split by `plan.training_sets`), from the
    --init weights where given; each stage's validation figures are `told` as it ends. The
    report, also written to `REPORT`."""
    report = json.loads(out.read(REPORT)) if settings.resume and out.has(REPORT) else {}
    report.update({"config": asdict(settings.cfg), "seed": settings.seed,
                   "device": settings.device.type})
    train_set, val_set = training_sets(meshes, settings.procedural, settings.seed)
    report["data"] = {"train": [n for n, _ in train_set], "validation": [n for n, _ in val_set]}

    def record(stage: str, entry: dict) -> None:
        report[stage] = entry
        out.write(REPORT, json.dumps(report, indent=1).encode())
        told(stage, entry["validation"])

    if "selector" in settings.stages and not (settings.resume
                                              and out.has("selector.safetensors")):
        # A new selector replaces any ensemble the report described.
        report.pop("selector_ensemble", None)
        record("selector", selector_stage(out, train_set, val_set, settings.cfg.selector,
                                          settings.seed, bar))
    network_stages = [s for s in settings.stages if s in NETWORK_STAGES]
    if network_stages:
        check_refined(settings, out, init)
        runner = _network_runner(settings, train_set, val_set, out, bar, report)
        if init is not None:
            report["init"] = init.where
        runner.start_from(init)
        for stage in network_stages:
            entry = runner.run(stage)
            if entry is not None:
                record(stage, entry)
    gains_done = all(out.has(f"{m}_gain.safetensors") for m in settings.cfg.gain.methods)
    if "gain" in settings.stages and not (settings.resume and gains_done):
        record("gain", gain_stage(out, train_set, val_set, settings.cfg.gain, settings.seed,
                                  network_weights(out, init), bar))
    out.write(REPORT, json.dumps(report, indent=1).encode())
    return report


def check_refined(settings: RunSettings, out: WeightsStore, init: WeightsStore | None) -> None:
    """Refuses, before any depth pair is made, a run whose LDM stages would refine a regressor
    that neither this run trains nor --init or a resumed --out gives."""
    refining = [s for s in settings.stages if s in ("vae", "ldm", "finetune")]
    if not (settings.cfg.ldm_refines_regressor and refining):
        return
    if ("regressor" in settings.stages or init is not None
            or (settings.resume and out.has("regressor.safetensors"))):
        return
    raise ValueError(f"--stages: {refining[0]} refines the regressor: run the regressor stage "
                     "first (or give its weights in --out or --init)")


def _network_runner(settings: RunSettings, train_set: NamedMeshes, val_set: NamedMeshes,
                    out: WeightsStore, bar: StageBar, report: dict) -> StageRunner:
    """The network stages' runner on freshly made depth pairs (their counts and time put in
    `report`)."""
    t0 = time.monotonic()
    data = settings.cfg.data
    with bar("data") as progress:
        train_pairs = training_pairs(train_set, data, settings.seed, settings.workers,
                                     lambda f: progress(f, ""))
    val_pairs = training_pairs(val_set, data, settings.seed + 1000, settings.workers)
    report["data"].update({"train_pairs": len(train_pairs.source),
                           "validation_pairs": len(val_pairs.source),
                           "seconds": time.monotonic() - t0})
    return StageRunner(out, settings.cfg, settings.seed, settings.device, settings.resume,
                       train_pairs, val_pairs, bar)


def selector_stage(out: WeightsStore, train_set: NamedMeshes, val_set: NamedMeshes,
                   config: SelectorTrainConfig, seed: int, bar: StageBar) -> dict:
    """Trains the twicing selector on noisy draws of the training meshes, writes
    selector.safetensors; its report entry, with validation on the held-out meshes."""
    from pipeline.enhance.training import selector as st
    from pipeline.enhance.weights.loading import weights_to_bytes

    rng = np.random.default_rng(seed)
    t0 = time.monotonic()
    with bar("selector data") as progress:
        examples = st.selector_examples(train_set, config, rng,
                                        progress=lambda f: progress(f, ""))
    data_seconds = time.monotonic() - t0
    with bar("selector") as progress:
        model, log = st.train_selector(examples, config, seed, progress)
    out.write("selector.safetensors", weights_to_bytes(model.state_dict(), asdict(config.model)))
    figures = st.validate_selector(model, val_set, config, np.random.default_rng(seed + 1000))
    return {**log, "data_seconds": data_seconds, "draws": len(examples),
            "vertices": int(sum(len(e.features) for e in examples)), "validation": figures}


def gain_stage(out: WeightsStore, train_set: NamedMeshes, val_set: NamedMeshes,
               config: GainTrainConfig, seed: int, weights: dict[str, bytes], bar: StageBar
               ) -> dict:
    """Trains a vertex gain network per method on noisy draws of the training meshes, enhanced
    by `weights` (a model left out: the shipped), writes <method>_gain.safetensors; its report
    entry, with validation on the held-out meshes."""
    from pipeline.enhance.training import gain as gt
    from pipeline.enhance.weights.loading import weights_to_bytes

    rng = np.random.default_rng(seed)
    t0 = time.monotonic()
    with bar("gain data") as progress:
        examples = gt.gain_examples(train_set, config, weights, rng,
                                    progress=lambda f: progress(f, ""))
    data_seconds = time.monotonic() - t0
    models, logs = {}, {}
    for method, method_examples in examples.items():
        with bar(f"{method} gain") as progress:
            models[method], logs[method] = gt.train_gain(method_examples, config, seed,
                                                         progress)
        out.write(f"{method}_gain.safetensors",
                  weights_to_bytes(models[method].state_dict(), asdict(config.model)))
    figures = gt.validate_gain(models, val_set, config, weights,
                               np.random.default_rng(seed + 1000))
    first = next(iter(examples.values()))
    return {"config": asdict(config), "methods": logs, "data_seconds": data_seconds,
            "draws": len(first), "meshes": list(dict.fromkeys(e.name for e in first)),
            "vertices": int(sum(len(e.features) for e in first)), "validation": figures}


def network_weights(out: WeightsStore, init: WeightsStore | None) -> dict[str, bytes]:
    """The weights the gain stage enhances with: each model from this run when it trained
    it, else from --init; models in neither are left to the shipped."""
    found = {}
    for name in ("selector", *DEPTH_NETWORKS):
        for store in (out, init):
            if store is not None and store.has(f"{name}.safetensors"):
                found[name] = store.read(f"{name}.safetensors")
                break
    return found
