"""Do the vertex gains hold on meshes they never saw? Leave one mesh out; prints JSON.

    .venv/bin/python benchmarks/enhance_gain_loo.py [--draws 4]

For each real training mesh of the shipped gains (the folder's meshes but the validation
meshes and the bunny): an LDM gain network trained as `volumesh train --stages gain` trains it,
on every other such mesh, then the held-out mesh under the enhance benchmark's protocol (1 m
high, 5 mm edges, ±1 cm noise along normals; no light remesh): C2M RMS of the selector alone,
of the LDM with the fixed `correction_gain`, and with the held-out gains. The depth networks
saw all of these meshes in training; only the gains are held out.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from enhance import bunny_protocol  # noqa: E402

from app.cli.train_data import training_sets  # noqa: E402
from pipeline.enhance import EnhanceConfig, enhance_mesh  # noqa: E402
from pipeline.enhance.metrics import c2m_summary  # noqa: E402
from pipeline.enhance.training.gain import GainTrainConfig, gain_examples, train_gain  # noqa: E402
from pipeline.enhance.weights.loading import weights_to_bytes  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--meshes", default=str(ROOT.parent / "shared" / "data" / "meshes"))
    ap.add_argument("--draws", type=int, default=GainTrainConfig.draws_per_mesh)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    config = GainTrainConfig(methods=("ldm",), draws_per_mesh=args.draws)
    train_set, _ = training_sets(Path(args.meshes), 0, args.seed)
    rng = np.random.default_rng(args.seed)
    examples = {name: gain_examples([(name, mesh)], config, None, rng)["ldm"]
                for name, mesh in train_set}
    report: dict = {"config": asdict(config), "meshes": {}}
    for held in examples:
        try:
            truth, noisy = bunny_protocol(Path(args.meshes), 0, name=held)
        except ValueError as exc:  # the protocol's remesher refuses non-manifold input
            report["meshes"][held] = {"error": str(exc)}
            continue
        rest = [e for name, ex in examples.items() if name != held for e in ex]
        model, _ = train_gain(rest, config, args.seed)
        weights = {"ldm_gain": weights_to_bytes(model.state_dict(), asdict(config.model))}
        base = EnhanceConfig(remesh_iterations=0, weights=weights)

        def rms(cfg: EnhanceConfig, noisy=noisy, truth=truth) -> float:
            return c2m_summary(enhance_mesh(noisy, cfg), truth)["c2m_rms_mm"]

        report["meshes"][held] = {
            "selector": rms(replace(base, method="selector")),
            "ldm_fixed_gain": rms(replace(base, learned_gain=False)),
            "ldm_held_out_gains": rms(base),
        }
        print(held, json.dumps(report["meshes"][held]), file=sys.stderr, flush=True)
    scored = [m for m in report["meshes"].values() if "error" not in m]
    report["mean"] = {k: float(np.mean([m[k] for m in scored])) for k in scored[0]}
    report["held_out_gains_better"] = sum(
        m["ldm_held_out_gains"] < m["ldm_fixed_gain"] for m in scored)
    report["scored"] = len(scored)
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
