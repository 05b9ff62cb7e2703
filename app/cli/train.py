"""`volumesh train`: trains the twicing selector (the pre-smoothing), the regressor, the VAE and
the U-Net + ControlNet, fine-tunes the three end to end, then the vertex gains of the mesh
update; writes weights, training.json and the model card. The data are `train_data`'s, the
network stages `train_stages`'."""

from __future__ import annotations

import json
import time
from dataclasses import asdict, replace
from pathlib import Path
from typing import Annotated

import typer

from app.cli import app
from app.cli.model_card import model_card

STAGES = "selector,regressor,vae,ldm,finetune,gain"
MESHES = Path("../shared/data/meshes")


@app.command()
def train(
    out: Annotated[Path, typer.Option("--out", help="Directory for checkpoints and weights.")],
    config: Annotated[str, typer.Option("--config", help="tiny | small | large")] = "small",
    resume: Annotated[bool, typer.Option("--resume", help="Continue from --out.")] = False,
    device: Annotated[str, typer.Option("--device", help="auto | cpu | cuda")] = "auto",
    seed: Annotated[int, typer.Option("--seed")] = 0,
    stages: Annotated[str, typer.Option("--stages", help="Comma-separated.")] = STAGES,
    meshes: Annotated[Path, typer.Option("--meshes", help="Folder of source meshes.")] = MESHES,
    procedural: Annotated[int, typer.Option("--procedural", help="Procedural shapes.")] = 6,
    budget_scale: Annotated[
        float, typer.Option("--budget-scale", help="Multiply every stage's steps and minutes.")
    ] = 1.0,
    workers: Annotated[
        int, typer.Option("--workers", min=1, help="Processes making the training pairs.")
    ] = 1,
    minutes: Annotated[
        float | None,
        typer.Option("--minutes", min=0.01,
                     help="Wall-clock cap per network stage (default: the config's)."),
    ] = None,
    poses: Annotated[
        int | None,
        typer.Option("--poses", min=1, help="Poses per source mesh (default: the config's)."),
    ] = None,
    mix: Annotated[
        str,
        typer.Option("--mix", help="Degradation mix of the pairs: full (every degradation) or "
                     "mesh (only what a mesh's renders carry, as the enhance stage meets)."),
    ] = "full",
    lr: Annotated[
        float | None,
        typer.Option("--lr", min=1e-7, max=1.0,
                     help="Peak learning rate of every network stage (default: the config's; "
                     "fine-tuning --init weights wants less, e.g. 2e-4)."),
    ] = None,
    loss_mask: Annotated[
        float | None,
        typer.Option("--loss-mask", min=0.001, max=1.0,
                     help="Leave pixels where an input is further than this (normalised depth) "
                     "from the clean render out of the losses (default: the config's, 0.05; "
                     "0.02 leaves out all that sees another surface)."),
    ] = None,
    init: Annotated[
        Path | None,
        typer.Option(
            "--init",
            help="Fine-tune the weights in this folder (e.g. the shipped ones): the regressor "
            "stage starts from its regressor.safetensors, the finetune stage from its "
            "vae/ldm.safetensors (then leave out the vae and ldm stages).",
        ),
    ] = None,
) -> None:
    """Train the enhancement models from meshes (never the bunny: it is the test model)."""
    from tqdm import tqdm

    from app.cli.paths import output_folder
    from app.cli.train_data import (
        gain_stage,
        network_weights,
        selector_stage,
        set_percent,
        training_pairs,
        training_sets,
    )
    from app.cli.train_stages import NETWORK_STAGES, StageRunner
    from pipeline.enhance.device import resolve_device

    cfg = run_config(config, budget_scale, poses, mix, minutes, lr, loss_mask)
    wanted = wanted_stages(stages, init)
    if not meshes.is_dir():  # an empty folder is fine: procedural shapes alone
        raise ValueError(f"--meshes: {meshes} is not a folder")
    dev = resolve_device(device)
    (output_folder(out) / "checkpoints").mkdir(exist_ok=True)
    report_path = out / "training.json"
    report = json.loads(report_path.read_text()) if resume and report_path.exists() else {}
    report.update({"config": asdict(cfg), "seed": seed, "device": dev.type})

    train_set, val_set = training_sets(meshes, procedural, seed)
    report["data"] = {"train": [n for n, _ in train_set], "validation": [n for n, _ in val_set]}
    if "selector" in wanted and not (resume and (out / "selector.safetensors").exists()):
        report["selector"] = selector_stage(out, train_set, val_set, cfg.selector, seed)
        # A new selector replaces any ensemble the report described.
        report.pop("selector_ensemble", None)
        report_path.write_text(json.dumps(report, indent=1))
    network_stages = [s for s in wanted if s in NETWORK_STAGES]
    if network_stages:
        t0 = time.monotonic()
        with tqdm(total=100, desc="data", unit="%") as bar:
            train_pairs = training_pairs(train_set, cfg.data, seed, workers,
                                         lambda f: set_percent(bar, f))
        val_pairs = training_pairs(val_set, cfg.data, seed + 1000, workers)
        report["data"].update({"train_pairs": len(train_pairs.source),
                               "validation_pairs": len(val_pairs.source),
                               "seconds": time.monotonic() - t0})
        runner = StageRunner(out, cfg, seed, dev, resume, train_pairs, val_pairs)
        if init is not None:
            report["init"] = str(init)
        runner.start_from(init)
        for stage in network_stages:
            entry = runner.run(stage)
            if entry is not None:
                report[stage] = entry
                report_path.write_text(json.dumps(report, indent=1))
                typer.echo(f"{stage}: {json.dumps(entry['validation'])}")
    gains_done = all((out / f"{m}_gain.safetensors").exists() for m in cfg.gain.methods)
    if "gain" in wanted and not (resume and gains_done):
        report["gain"] = gain_stage(out, train_set, val_set, cfg.gain, seed,
                                    network_weights(out, init))
    report_path.write_text(json.dumps(report, indent=1))
    (out / "MODEL_CARD.md").write_text(model_card(report))


def run_config(config: str, budget_scale: float, poses: int | None, mix: str,
               minutes: float | None, lr: float | None, loss_mask: float | None):
    """The named configuration with the command line's edits; ValueError names a bad option."""
    from pipeline.enhance.training import config as tc
    from pipeline.enhance.training.data import MIXES, with_mix

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
    return cfg


def wanted_stages(stages: str, init: Path | None) -> list[str]:
    """The --stages list, checked against each other and against --init's folder."""
    wanted = [s.strip() for s in stages.split(",") if s.strip()]
    for s in wanted:
        if s not in STAGES.split(","):
            raise ValueError(f"--stages: unknown stage {s!r}")
    if init is not None:
        missing = [n for n in ("regressor", "vae", "ldm")
                   if not (init / f"{n}.safetensors").exists()]
        if missing:
            raise ValueError(f"--init: {init} has no {', '.join(missing)}.safetensors")
        if {"vae", "ldm"} & set(wanted):
            raise ValueError("--init: leave out the vae and ldm stages (finetune starts from "
                             "the folder's)")
    return wanted


@app.command("selector-ensemble")
def selector_ensemble(
    out: Annotated[Path, typer.Option("--out", help="The ensemble's .safetensors file.")],
    members: Annotated[list[Path], typer.Argument(
        help="selector.safetensors files of `volumesh train --stages selector` runs with "
        "different seeds.")],
) -> None:
    """Write the ensemble of trained selectors: the mean of their blend weights."""
    from pipeline.enhance.weights.loading import load_selector, selector_ensemble_to_bytes

    if len(set(members)) < 2 or len(set(members)) < len(members):
        raise ValueError("selector-ensemble: give two or more different selector files")
    if not out.parent.is_dir():
        raise ValueError(f"selector-ensemble: --out: {out.parent} is not a directory")
    data = []
    for path in members:
        if not path.is_file():
            raise ValueError(f"selector-ensemble: {path} is not a file")
        data.append(path.read_bytes())
        try:
            load_selector(data[-1])
        except Exception as exc:  # whatever a foreign file makes safetensors or torch raise
            raise ValueError(f"selector-ensemble: {path} is not a selector file ({exc})"
                             ) from None
    out.write_bytes(selector_ensemble_to_bytes(data))
