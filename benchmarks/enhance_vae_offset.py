"""A/B of `VAEConfig.encode_correction` (the VAE encoder also reads the depth's offset from
the guide) at an equal CPU budget; prints JSON.

    .venv/bin/python benchmarks/enhance_vae_offset.py > vae_offset.json   # about 50 min, 2 cores

For each setting, on the same pairs (training meshes of shared/, 4 poses each, plus 4
procedural shapes; held-apart spot and fandisk, 2 poses each): the VAE stage, then U-Net +
ControlNet, then end-to-end fine-tuning, with the `small` configuration's networks, crop and
batch and these step counts. Depth figures are `validate_ldm`'s (thousandths of the depth
range): `vae_clean_latent` is what the latent can carry at best, `vae_degraded_latent` where
sampling starts, `ldm_*` the whole enhancer. Figures after the VAE stage alone come first.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pipeline.enhance.training.data import DataConfig, make_pairs, procedural_meshes  # noqa: E402
from pipeline.io.mesh_io import read_mesh  # noqa: E402

TRAIN = ("beetle", "cheburashka", "cow", "homer", "rocker-arm", "suzanne", "teapot")
VALIDATION = ("spot", "fandisk")


def rmse(scores: dict) -> dict:
    return {k: round(v["rmse_permille"], 3) for k, v in scores.items() if isinstance(v, dict)}


def run(train, val, encode_correction: bool, args) -> dict:
    import torch

    from pipeline.enhance.pipelines.depth_ldm import LDMModels
    from pipeline.enhance.training.config import CONFIGS, StageBudget
    from pipeline.enhance.training.stages import train_finetune, train_ldm, train_vae
    from pipeline.enhance.training.validate import validate_ldm

    small = CONFIGS["small"]
    config = replace(
        small,
        vae=replace(small.vae, encode_correction=encode_correction),
        vae_budget=StageBudget(args.vae_steps, 600.0),
        ldm_budget=StageBudget(args.ldm_steps, 600.0, 5e-4),
        finetune_budget=StageBudget(args.finetune_steps, 600.0, 2e-4),
    )
    cpu = torch.device("cpu")
    vae, _ = train_vae(train, config, args.seed, cpu)
    after_vae = validate_ldm(None, vae, val, args.views, cpu)
    unet, control, _ = train_ldm(train, vae, config, args.seed, cpu)
    models, _ = train_finetune(train, LDMModels(vae, unet, control), config, args.seed, cpu)
    final = validate_ldm((models.unet, models.controlnet), models.vae, val, args.views, cpu)
    return {"after_vae": rmse(after_vae), "after_finetune": rmse(final)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--meshes", default=str(ROOT.parent / "shared" / "data" / "meshes"))
    ap.add_argument("--vae-steps", type=int, default=800)
    ap.add_argument("--ldm-steps", type=int, default=2000)
    ap.add_argument("--finetune-steps", type=int, default=800)
    ap.add_argument("--poses", type=int, default=4)
    ap.add_argument("--views", type=int, default=24)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    meshes = Path(args.meshes)
    train_meshes = [(n, read_mesh(meshes / f"{n}.obj")) for n in TRAIN]
    train_meshes += procedural_meshes(np.random.default_rng(0), 4)
    train = make_pairs(train_meshes, DataConfig(poses_per_mesh=args.poses), 123)
    val_meshes = [(n, read_mesh(meshes / f"{n}.obj")) for n in VALIDATION]
    val = make_pairs(val_meshes, DataConfig(poses_per_mesh=2), 5)
    report = {
        "pairs": {"train": len(train.source), "validation": len(val.source)},
        "steps": {"vae": args.vae_steps, "ldm": args.ldm_steps, "finetune": args.finetune_steps},
        "units": "1e-3 of depth range",
    }
    for flag in (True, False):
        report[f"encode_correction_{str(flag).lower()}"] = run(train, val, flag, args)
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
