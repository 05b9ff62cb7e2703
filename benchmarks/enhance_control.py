"""The LDM's control: is its depth gain over the regressor the diffusion model's, or would any
second network trained on what the regressor leaves, with the same data and budget, get it?

    .venv/bin/python benchmarks/enhance_control.py [--steps 4800] [--minutes 45] [--out DIR]

The shipped LDM refines the shipped regressor (`LDMModels.refines`): 4 800 end-to-end steps
(batch 8, 128² crops, peak learning rate 2e-4) on the pairs of `volumesh train --config small
--procedural 12 --seed 21` (model card). The control is a plain residual U-Net of the
regressor's size, started from the regressor's weights with its output convolution zeroed
(so it starts as the identity, as the LDM's zero convolutions do), trained with the same
steps, batch, crops and learning rate on the same pairs to correct the frozen regressor's
estimate. Both are scored on the same held-apart renders, with the full degradation mix and
with the enhance benchmark's vertex noise alone. Prints JSON (about an hour on 2 CPU cores).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from enhance import VERTEX_NOISE_ONLY, network_predictions  # noqa: E402

from app.cli.train_data import training_pairs, training_sets  # noqa: E402
from pipeline.enhance.models.regressor import RefinedRegressor  # noqa: E402
from pipeline.enhance.training import config as tc  # noqa: E402
from pipeline.enhance.training import stages as tr  # noqa: E402
from pipeline.enhance.training.data import make_pairs  # noqa: E402
from pipeline.enhance.training.validate import depth_scores, validate_ldm, validate_regressor  # noqa: E402
from pipeline.enhance.weights import shipped_bytes  # noqa: E402
from pipeline.enhance.weights.loading import load_ldm, load_regressor, regressor_to_bytes  # noqa: E402


def identity_start(regressor_bytes: bytes) -> nn.Module:
    """The regressor's network with its output convolution zeroed: correction 0."""
    model = load_regressor(regressor_bytes)
    nn.init.zeros_(model.conv_out.weight)
    nn.init.zeros_(model.conv_out.bias)
    return model


def vertex_noise_scores(control_bytes: bytes, val_set, views: int) -> dict:
    """The enhance benchmark's degradation alone on the held-apart meshes, the same renders
    as its `vertex_noise_only` figures (seed 0): base, regressor, control and LDM (4 steps)."""
    named = [next((n, m) for n, m in val_set if n == name) for name in ("spot", "fandisk")]
    pairs = make_pairs(named, VERTEX_NOISE_ONLY, 2000)
    idx = np.unique(np.linspace(0, len(pairs.source) - 1, views).round().astype(np.int64))
    # The control loads as the regressor (`load_regressor` reads a `RefinedRegressor`).
    controlled = network_predictions({"regressor": control_bytes}, pairs, idx, ())
    preds = {"presmoothed": pairs.degraded_n[idx], "control": controlled["regressor"],
             **network_predictions(None, pairs, idx, (4,))}
    return {"views": len(idx), **{k: depth_scores(p, pairs, idx) for k, p in preds.items()}}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--meshes", type=Path, default=ROOT.parent / "shared" / "data" / "meshes")
    ap.add_argument("--seed", type=int, default=21, help="the LDM fine-tune's seed")
    ap.add_argument("--steps", type=int, default=4800, help="the LDM fine-tune's steps")
    ap.add_argument("--minutes", type=float, default=45.0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--poses", type=int, default=12, help="poses per mesh (12: the LDM's)")
    ap.add_argument("--views", type=int, default=24, help="validation renders scored")
    ap.add_argument("--out", type=Path, default=None,
                    help="folder for the control's weights (as regressor.safetensors)")
    args = ap.parse_args()
    device = torch.device("cpu")
    config = tc.CONFIGS["small"]
    config = replace(config, data=replace(config.data, poses_per_mesh=args.poses),
                     regressor_budget=tc.StageBudget(args.steps, args.minutes,
                                                     config.finetune_budget.lr))
    t0 = time.monotonic()
    train_set, val_set = training_sets(args.meshes, 12, args.seed)
    with tqdm(total=100, desc="pairs", unit="%") as bar:
        train_pairs = training_pairs(train_set, config.data, args.seed, args.workers,
                                     lambda f: bar.update(round(100 * f) - bar.n))
    val_pairs = training_pairs(val_set, config.data, args.seed + 1000, args.workers)
    data_s = time.monotonic() - t0

    regressor = load_regressor(shipped_bytes("regressor"))
    model = RefinedRegressor(regressor, identity_start(shipped_bytes("regressor")))
    with tqdm(total=args.steps, desc="control", unit="step") as bar:
        model, log = tr.train_regressor(
            train_pairs, config, args.seed + 3, device,
            progress=lambda f, msg: (bar.update(round(f * args.steps) - bar.n),
                                     bar.set_postfix_str(msg)),
            initial=model,  # type: ignore[arg-type]
        )
    control_bytes = regressor_to_bytes(model, half=True)
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        # As regressor.safetensors: `enhance_gain.py --weights DIR` then runs it on meshes.
        (args.out / "regressor.safetensors").write_bytes(control_bytes)
    ldm = load_ldm(shipped_bytes("vae"), shipped_bytes("ldm"))
    report = {
        "seed": args.seed,
        "train_pairs": len(train_pairs.source),
        "validation_pairs": len(val_pairs.source),
        "data_seconds": data_s,
        "control_steps": log[-1]["step"] if log else 0,
        "control_train_seconds": log[-1]["seconds"] if log else 0.0,
        "control_final_loss": log[-1]["loss"] if log else None,
        "units": "1e-3 of depth range",
        "full_mix": {
            "control": validate_regressor(model, val_pairs, args.views, device),
            "ldm": validate_ldm((ldm.unet, ldm.controlnet), ldm.vae, val_pairs, args.views,
                                device, ldm.refines),
        },
        "vertex_noise_only": vertex_noise_scores(control_bytes, val_set, 24),
    }
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
