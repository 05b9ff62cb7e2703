"""`volumesh train`: trains the twicing selector (the pre-smoothing), the regressor, the VAE and
the U-Net + ControlNet, then fine-tunes the three end to end; writes weights."""

from __future__ import annotations

import json
import time
from dataclasses import asdict, replace
from pathlib import Path
from typing import Annotated

import typer

from app.cli import app
from app.cli.model_card import model_card

VALIDATION_MESHES = ("spot", "fandisk")
TEST_MESH_PREFIX = "stanford-bunny"
STAGES = "selector,regressor,vae,ldm,finetune"
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

    from pipeline.enhance import train as tr
    from pipeline.enhance import train_config as tc
    from pipeline.enhance import train_loop as tl
    from pipeline.enhance.data import MIXES, with_mix
    from pipeline.enhance.device import resolve_device
    from pipeline.enhance.inference import ldm_to_bytes, weights_to_bytes
    from pipeline.enhance.pipelines.depth_ldm import LDMModels
    from pipeline.enhance.validate import validate_ldm, validate_regressor

    if config not in tc.CONFIGS:
        raise ValueError(f"--config: {config!r} is not one of {', '.join(tc.CONFIGS)}")
    cfg = tc.scaled(tc.CONFIGS[config], budget_scale) if budget_scale != 1.0 else tc.CONFIGS[config]
    if poses is not None:
        cfg = replace(cfg, data=replace(cfg.data, poses_per_mesh=poses))
    if mix not in MIXES:
        raise ValueError(f"--mix: {mix!r} is not one of {', '.join(MIXES)}")
    cfg = replace(cfg, data=with_mix(cfg.data, mix))
    if minutes is not None:
        cfg = tc.capped(cfg, minutes)
    if lr is not None:
        cfg = tc.with_lr(cfg, lr)
    if loss_mask is not None:
        cfg = replace(cfg, loss_mask_threshold_n=loss_mask)
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
    dev = resolve_device(device)
    device = dev.type
    out.mkdir(parents=True, exist_ok=True)
    (out / "checkpoints").mkdir(exist_ok=True)
    report_path = out / "training.json"
    report = json.loads(report_path.read_text()) if resume and report_path.exists() else {}
    report.update({"config": asdict(cfg), "seed": seed, "device": device})

    train_set, val_set = training_sets(meshes, procedural, seed)
    report["data"] = {"train": [n for n, _ in train_set], "validation": [n for n, _ in val_set]}
    if "selector" in wanted:
        wanted.remove("selector")
        if not (resume and (out / "selector.safetensors").exists()):
            report["selector"] = selector_stage(out, train_set, val_set, cfg.selector, seed)
            report_path.write_text(json.dumps(report, indent=1))
    if wanted:
        t0 = time.monotonic()
        with tqdm(total=100, desc="data", unit="%") as bar:
            train_pairs = training_pairs(train_set, cfg.data, seed, workers,
                                         lambda f: _bar(bar, f))
        val_pairs = training_pairs(val_set, cfg.data, seed + 1000, workers)
        report["data"].update(
            {
                "train_pairs": len(train_pairs.source),
                "validation_pairs": len(val_pairs.source),
                "seconds": time.monotonic() - t0,
            }
        )

    def checkpoint_io(stage: str):
        path = out / "checkpoints" / f"{stage}.pt"
        state = None
        if resume and path.exists():
            state = tl.checkpoint_from_bytes(path.read_bytes())

        def save(ck: dict) -> None:
            tmp = path.with_suffix(".tmp")
            tmp.write_bytes(tl.checkpoint_to_bytes(ck))
            tmp.replace(path)  # atomic: an interrupted write never spoils the last checkpoint

        return state, save

    def finished(name: str) -> bytes | None:
        path = out / _stage_file(name)
        return path.read_bytes() if resume and path.exists() else None

    vae, nets, regressor, initial = None, None, None, None
    if init is not None:
        from pipeline.enhance.inference import load_ldm, load_regressor

        report["init"] = str(init)
        initial = regressor = load_regressor((init / "regressor.safetensors").read_bytes())
        models = load_ldm((init / "vae.safetensors").read_bytes(),
                          (init / "ldm.safetensors").read_bytes())
        vae, nets = models.vae.to(dev), (models.unet.to(dev), models.controlnet.to(dev))
    trained_regressor = finished("regressor")
    if trained_regressor is not None:
        from pipeline.enhance.inference import load_regressor

        regressor = load_regressor(trained_regressor)
    if regressor is not None:
        regressor.to(dev)

    def refines(stage: str):
        """The regressor the LDM's stages refine (None when the config does not)."""
        if not cfg.ldm_refines_regressor:
            return None
        if regressor is None:
            raise ValueError(f"--stages: {stage} refines the regressor: run the regressor "
                             "stage first (or give its weights in --out or --init)")
        return regressor

    for stage in wanted:
        done = finished(stage)
        if done is not None:
            # A finished stage is kept; the VAE and LDM are loaded for the stages after them.
            from pipeline.enhance.inference import load_ldm, load_vae

            if stage == "vae":
                vae = load_vae(done).to(dev)
            if stage == "ldm" and vae is not None:
                models = load_ldm(finished("vae") or b"", done)
                vae, nets = models.vae.to(dev), (models.unet.to(dev), models.controlnet.to(dev))
            continue
        resume_state, save = checkpoint_io(stage)
        bar, cb = _stage_bar(stage)
        t_stage = time.monotonic()
        if stage == "regressor":
            regressor, log = tr.train_regressor(
                train_pairs, cfg, seed, dev, resume_state, save, cb, initial
            )
            data = weights_to_bytes(regressor.state_dict(), asdict(regressor.config))
            figures = validate_regressor(regressor, val_pairs, cfg.validation_views, dev)
        elif stage == "vae":
            vae, log = tr.train_vae(train_pairs, cfg, seed, dev, resume_state, save, cb,
                                    refines("vae"))
            data = weights_to_bytes(vae.state_dict(), asdict(cfg.vae))
            figures = validate_ldm(None, vae, val_pairs, cfg.validation_views, dev,
                                   refines("vae"))
        elif stage == "ldm":
            if vae is None:
                raise ValueError("--stages: ldm needs the vae stage (or its weights in --out)")
            unet, control, log = tr.train_ldm(
                train_pairs, vae, cfg, seed, dev, resume_state, save, cb, refines("ldm")
            )
            nets = (unet, control)
            models = LDMModels(vae, unet, control, refines("ldm"))
            data = ldm_to_bytes(models, asdict(cfg.unet))
            figures = validate_ldm(nets, vae, val_pairs, cfg.validation_views, dev,
                                   models.refines)
        else:
            if vae is None or nets is None:
                raise ValueError("--stages: finetune needs the vae and ldm stages (or their "
                                 "weights in --out)")
            models, log = tr.train_finetune(
                train_pairs, LDMModels(vae, *nets, refines("finetune")), cfg, seed, dev,
                resume_state, save, cb,
            )
            # The stage-wise weights stay beside the fine-tuned ones for comparison.
            (out / "pretrained").mkdir(exist_ok=True)
            for name in ("vae", "ldm"):
                if (out / f"{name}.safetensors").exists():  # absent when fine-tuning --init
                    (out / f"{name}.safetensors").replace(
                        out / "pretrained" / f"{name}.safetensors"
                    )
            vae, nets = models.vae, (models.unet, models.controlnet)
            vae_bytes = weights_to_bytes(vae.state_dict(), asdict(cfg.vae))
            (out / "vae.safetensors").write_bytes(vae_bytes)
            (out / "ldm.safetensors").write_bytes(
                ldm_to_bytes(models, asdict(cfg.unet)))
            data = b"end-to-end fine-tuned: see vae.safetensors and ldm.safetensors"
            figures = validate_ldm(nets, vae, val_pairs, cfg.validation_views, dev,
                                   models.refines)
        bar.close()
        (out / _stage_file(stage)).write_bytes(data)
        report[stage] = {
            "steps": log[-1]["step"] if log else 0,
            "lr": getattr(cfg, f"{stage}_budget").lr,
            "train_seconds": log[-1]["seconds"] if log else 0.0,
            "wall_seconds_this_run": time.monotonic() - t_stage,
            "final_loss": log[-1]["loss"] if log else None,
            "loss_log": log[:: max(1, len(log) // 50)],
            "validation": figures,
        }
        report_path.write_text(json.dumps(report, indent=1))
        typer.echo(f"{stage}: {json.dumps(figures)}")
    report_path.write_text(json.dumps(report, indent=1))
    (out / "MODEL_CARD.md").write_text(model_card(report))


def selector_stage(out: Path, train_set, val_set, config, seed: int) -> dict:
    """Trains the twicing selector on noisy draws of the training meshes, writes
    selector.safetensors; its report entry, with validation on the held-out meshes."""
    import numpy as np
    from tqdm import tqdm

    from pipeline.enhance import selector_training as st
    from pipeline.enhance.inference import weights_to_bytes

    rng = np.random.default_rng(seed)
    t0 = time.monotonic()
    with tqdm(total=100, desc="selector data", unit="%") as data_bar:
        examples = st.selector_examples(train_set, config, rng,
                                        progress=lambda f: _bar(data_bar, f))
    data_seconds = time.monotonic() - t0
    bar, cb = _stage_bar("selector")
    model, log = st.train_selector(examples, config, seed, cb)
    bar.close()
    (out / "selector.safetensors").write_bytes(
        weights_to_bytes(model.state_dict(), asdict(config.model))
    )
    figures = st.validate_selector(model, val_set, config, np.random.default_rng(seed + 1000))
    typer.echo(f"selector: {json.dumps(figures)}")
    return {**log, "data_seconds": data_seconds, "draws": len(examples),
            "vertices": int(sum(len(e.features) for e in examples)), "validation": figures}


POSES_PER_JOB = 8


def training_sets(meshes: Path, procedural: int, seed: int) -> tuple[list, list]:
    """(train, validation) lists of (name, mesh): the folder's meshes but the test model,
    split by mesh (VALIDATION_MESHES held apart), and `procedural` seeded shapes (one more
    held apart)."""
    import numpy as np

    from pipeline.enhance.data import procedural_meshes
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

    from pipeline.enhance.data import concat_pairs, make_pairs

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


def _stage_file(stage: str) -> str:
    """The file whose presence marks a stage finished (fine-tuning rewrites vae and ldm)."""
    return "finetune.done" if stage == "finetune" else f"{stage}.safetensors"


def _stage_bar(stage: str):
    """A progress bar for a training stage and the (fraction, text) callback that moves it."""
    from tqdm import tqdm

    bar = tqdm(total=1000, desc=stage)

    def cb(f: float, text: str) -> None:
        bar.n = int(f * 1000)
        bar.set_postfix_str(text, refresh=False)
        bar.refresh()

    return bar, cb


def _bar(bar, fraction: float) -> None:
    bar.n = int(fraction * 100)
    bar.refresh()
