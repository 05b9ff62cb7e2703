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
    from pipeline.enhance.data import MIXES, with_mix
    from pipeline.enhance.inference import ldm_to_bytes, weights_to_bytes
    from pipeline.enhance.pipelines.depth_ldm import LDMModels
    from pipeline.enhance.validate import validate_ldm, validate_regressor

    if config not in tr.CONFIGS:
        raise ValueError(f"--config: {config!r} is not one of {', '.join(tr.CONFIGS)}")
    cfg = tr.scaled(tr.CONFIGS[config], budget_scale) if budget_scale != 1.0 else tr.CONFIGS[config]
    if poses is not None:
        cfg = replace(cfg, data=replace(cfg.data, poses_per_mesh=poses))
    if mix not in MIXES:
        raise ValueError(f"--mix: {mix!r} is not one of {', '.join(MIXES)}")
    cfg = replace(cfg, data=with_mix(cfg.data, mix))
    if minutes is not None:
        cfg = tr.capped(cfg, minutes)
    if lr is not None:
        cfg = tr.with_lr(cfg, lr)
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
    dev = tr.resolve_device(device)
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
            state = tr.checkpoint_from_bytes(path.read_bytes())

        def save(ck: dict) -> None:
            tmp = path.with_suffix(".tmp")
            tmp.write_bytes(tr.checkpoint_to_bytes(ck))
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


def model_card(report: dict) -> str:
    """Markdown model card from the training report (config, data, time, validation)."""
    cfg = report["config"]
    lines = [
        "# volumesh depth enhancer weights",
        "",
        "Trained in-house by `volumesh train`'s stages (how they were run: below); no "
        "pretrained weights were used.",
        "",
        f"- configuration: `{cfg['name']}`, seed {report['seed']}, device `{report['device']}`",
        *([f"- {report['note']}"] if report.get("note") else []),
        f"- training meshes: {', '.join(report['data']['train'])}",
        f"- validation meshes (held apart by mesh): {', '.join(report['data']['validation'])}",
        "- never trained on: stanford-bunny (the benchmark's test model)",
        *_pairs_lines(report),
        *_selector_lines(report),
        "- the depth networks' copies shipped in `pipeline/enhance/weights` are stored as "
        "float16 and load as float32; mesh-level figures: README, Enhancement "
        "(`benchmarks/enhance.py`)",
        "",
        "| stage | steps | training time (min) | final loss |",
        "| --- | --- | --- | --- |",
    ]
    for stage in ("regressor", "vae", "ldm", "finetune"):
        if stage in report:
            r = report[stage]
            loss = r["final_loss"]
            lines.append(
                f"| {stage} | {r['steps']} | {r['train_seconds'] / 60:.1f} | "
                f"{loss if loss is None else round(loss, 4)} |"
            )
    lines += [
        "",
        "Validation (held-apart meshes; depth RMSE in thousandths of the view's depth range,",
        "about 1.6 mm per unit on a 1 m model; `edge` = 3-pixel band at depth edges):",
        "",
        "| stage | method | RMSE | edge RMSE |",
        "| --- | --- | --- | --- |",
    ]
    for stage in ("regressor", "vae", "ldm", "finetune"):
        for method, fig in report.get(stage, {}).get("validation", {}).items():
            if isinstance(fig, dict):
                lines.append(
                    f"| {stage} | {method} | {fig['rmse_permille']:.3f} | "
                    f"{fig['edge_rmse_permille']:.3f} |"
                )
    lines += _continuation_lines(report.get("continued"), "refined" in report)
    lines += _refined_lines(report.get("refined"))
    lines += ["", "Config (of the first run above):", "", "```json", json.dumps(cfg, indent=1),
              "```", ""]
    return "\n".join(lines)


def _pairs_lines(report: dict) -> list[str]:
    """The card's lines on the depth networks' data (absent from a selector-only run)."""
    cfg = report["config"]
    if "train_pairs" not in report["data"]:
        return []
    return [
        f"- pairs: {report['data']['train_pairs']} training, "
        f"{report['data']['validation_pairs']} validation, "
        f"{cfg['data']['resolution']}² normalised depth (per view, relative to the bounding "
        "sphere); degradations: vertex noise along normals (amplitude "
        f"{cfg['data']['noise_fraction'][0]}–{cfg['data']['noise_fraction'][1]} of the largest "
        "extent, or below the lower bound for a share "
        f"{cfg['data'].get('light_noise_probability', 0)} of the poses), Azure-Kinect-like "
        "axial noise and flying pixels, holes, 4x "
        "down-then-up sampling; synthetic colour (albedo patches shaded by the clean normals) on "
        f"a share {cfg['data'].get('color_probability', 0)} of the poses, its Canny edges an input",
        f"- crops {cfg['crop']}², batch {cfg['batch']}, AdamW, warm-up + cosine schedule",
        "- source meshes are remeshed isotropically by the pipeline's remesh stage (edge "
        f"{cfg['data']['edge_fraction'][0]}–{cfg['data']['edge_fraction'][1]} of the largest "
        "extent) before the noise, as the enhance stage receives them",
        f"- the networks correct the render of the noisy mesh after {_presmoothing(cfg['data'])}, "
        "reading the noisy mesh's own render beside it (its offset from the smoothed one)",
        "- stages: the regressor (the plain baseline); the VAE; U-Net + ControlNet "
        "(v-prediction); then end-to-end fine-tuning of VAE, U-Net and ControlNet through the "
        f"unrolled {'/'.join(map(str, cfg['finetune_steps']))}-step DDIM sampler at strength "
        f"{cfg['finetune_strength']} on the decoded depth error",
    ]


def _selector_lines(report: dict) -> list[str]:
    """The card's lines on the twicing selector (the networks' pre-smoothing)."""
    if "selector" not in report:
        return []
    r, c = report["selector"], report["config"]["selector"]
    lines = [
        "- **selector** (`selector.safetensors`, `models/twicing_selector.py`): a per-vertex "
        f"MLP ({c['model']['hidden']} wide) weighing twicings at "
        f"{'/'.join(map(str, c['model']['iterations']))} iterations; it is the enhance stage's "
        "pre-smoothing and `--method selector`. Trained on "
        f"{r['draws']} noisy draws of the training meshes ({r['vertices']} vertices; edges "
        f"{c['edge_fraction'][0]}–{c['edge_fraction'][1]} of the largest extent, uniform noise "
        f"along normals of {c['noise_to_edge'][0]}–{c['noise_to_edge'][1]} edge lengths) for "
        f"{r['steps']} steps ({r['train_seconds'] / 60:.1f} min, data "
        f"{r['data_seconds'] / 60:.1f} min), loss: the blend's squared distance to the truth.",
        *([f"  Run as `{r['command']}` on {r['device']}, training meshes "
           f"{', '.join(r['data']['train'])}."] if "command" in r else []),
        "",
        "  Held-out meshes, one draw each, RMS distance to the truth in thousandths of the "
        "extent:",
        "",
        "  | mesh | noisy | best single count | adaptive twicing | selector |",
        "  | --- | --- | --- | --- | --- |",
    ]
    for name, f in r["validation"].items():
        lines.append(f"  | {name} | {f['noisy']:.3f} | {f['best_count']:.3f} | "
                     f"{f['adaptive_twicing']:.3f} | {f['selector']:.3f} |")
    return lines + [""]


def _presmoothing(data: dict) -> str:
    iterations, passes = data.get("presmooth_iterations", 0), data.get("presmooth_passes", 1)
    if data.get("presmooth_learned") and iterations > 0:
        return "the shipped selector's per-vertex blend of twicings (`learned_twicing`)"
    if data.get("presmooth_adaptive"):
        return (f"twicing ({passes} passes) with its count chosen per vertex among several, "
                f"a pilot at {iterations} iterations estimating each count's bias")
    if passes == 1:
        return f"{iterations} Laplacian smoothing iterations (λ 0.5)"
    return (f"{iterations} Laplacian smoothing iterations (λ 0.5) in {passes} passes "
            "(twicing: each pass smooths what the passes before left and adds it back)")


def _continuation_lines(continued: dict | None, refined: bool = False) -> list[str]:
    """The card's section on a later fine-tuning of these weights (`volumesh train --init`);
    `refined`: the LDM was trained again after it (`_refined_lines`)."""
    if not continued:
        return []
    shipped = ("the shipped regressor; the vae and ldm were trained again, next section"
               if refined else "these are the shipped weights")
    lines = [
        "",
        f"## Fine-tuned since ({shipped})",
        "",
        f"- {continued['note']}",
        f"- the networks now correct the render after {_presmoothing(continued['data'])}; "
        "what the enhance stage feeds them: `EnhanceConfig.presmooth_*`",
        *([f"- {continued['inference_note']}"] if continued.get("inference_note") else []),
        f"- pairs: {continued['train_pairs']} training, {continued['validation_pairs']} "
        "validation, same meshes and split as above",
        "",
        "| stage | steps | peak lr | training time (min) | final loss |",
        "| --- | --- | --- | --- | --- |",
    ]
    for stage in ("regressor", "finetune"):
        r = continued[stage]
        lines.append(f"| {stage} | {r['steps']} | {r['lr']} | {r['train_seconds'] / 60:.1f} | "
                     f"{round(r['final_loss'], 4)} |")
    lines += ["", "Validation on the new pre-smoothing, before and after (as above):", "",
              "| stage | method | RMSE before | RMSE after | edge before | edge after |",
              "| --- | --- | --- | --- | --- | --- |"]
    for stage in ("regressor", "finetune"):
        before, after = continued[stage]["validation_before"], continued[stage]["validation"]
        for method, fig in after.items():
            if isinstance(fig, dict):
                b = before[method]
                lines.append(
                    f"| {stage} | {method} | {b['rmse_permille']:.3f} | "
                    f"{fig['rmse_permille']:.3f} | {b['edge_rmse_permille']:.3f} | "
                    f"{fig['edge_rmse_permille']:.3f} |"
                )
    return lines


def _refined_lines(refined: dict | None) -> list[str]:
    """The card's section on re-training the LDM to refine the regressor (`LDMModels.refines`):
    the report of a `--init ... --stages finetune` run, with its command."""
    if not refined:
        return []
    f, data = refined["finetune"], refined["data"]
    v = f["validation"]
    lines = [
        "",
        "## The LDM refines the regressor (these are the shipped vae and ldm)",
        "",
        "- `ldm.safetensors` carries the regressor it refines (its `refines.*` tensors are the "
        "shipped `regressor.safetensors`, its config in the metadata): the LDM encodes, denoises "
        "and decodes around the regressor's estimate instead of the pre-smoothed base "
        "(`LDMModels.refines`, `TrainConfig.ldm_refines_regressor`; the split of CorrDiff, "
        "Mardani et al. 2023). The regressor stays frozen; the VAE, U-Net and ControlNet learn "
        "what it leaves.",
        f"- run as `{refined['command']}` on {refined['device']}, from the weights above: "
        f"{f['steps']} end-to-end steps in {f['train_seconds'] / 60:.1f} minutes, final loss "
        f"{f['final_loss']:.4f}; pairs in {data['seconds'] / 60:.1f} minutes",
        f"- pairs: {data['train_pairs']} training, {data['validation_pairs']} validation, same "
        f"meshes and split as above, the base depth after {_presmoothing(refined['config_data'])}"
        ", as the enhance stage now feeds the networks",
        "",
        f"Validation, {v['views']} held-apart renders (as above; `regressor`: the embedded "
        "regressor alone):",
        "",
        "| method | RMSE | edge RMSE |",
        "| --- | --- | --- |",
    ]
    lines += [f"| {k} | {x['rmse_permille']:.3f} | {x['edge_rmse_permille']:.3f} |"
              for k, x in v.items() if isinstance(x, dict)]
    return lines + ["", refined["note"]]


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
