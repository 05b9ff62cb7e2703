"""Two sets of weights side by side under the protocol and each noise model; prints JSON.

    .venv/bin/python benchmarks/enhance_weights.py --before DIR [--after DIR] [--meshes DIR]
        [--mesh NAME ...] [--noise uniform|gaussian|laplace ...] [--seed N]

On each mesh (by default spot and fandisk, held apart for validation, and the bunny, the test
model) and noise model of `enhance_noise.py`, for the weights in --before and in --after
(default: the shipped): the pre-smoothing (the selector's blend, then the midrange estimator),
the `classical` method, the regressor and the LDM (at 4 steps and at 1), each as C2M RMS mm
and mean normal error °, and each method's RMS after / before. The classical smoothers do
not depend on the weights: `enhance_noise.py` gives them.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from enhance_protocol import (  # noqa: E402
    MESHES,
    NOISE_KINDS,
    protocol_noise,
    protocol_truth,
    run_method,
    score,
    weights_folder,
)

from pipeline.enhance import EnhanceConfig  # noqa: E402
from pipeline.enhance.inference import selector_presmoothed  # noqa: E402
from pipeline.enhance.presmooth.midrange import BoundedNoiseConfig  # noqa: E402
from pipeline.enhance.weights import shipped_bytes  # noqa: E402
from pipeline.enhance.weights.loading import load_selector  # noqa: E402

DEFAULT_MESHES = ("spot", "fandisk", "stanford-bunny")
RUNS = {"classical": EnhanceConfig(method="classical"),
        "regressor": EnhanceConfig(method="regressor"),
        "ldm": EnhanceConfig(method="ldm"),
        # Whether the diffusion steps do anything: the LDM at one step against its four.
        "ldm_1_step": EnhanceConfig(method="ldm", steps=1)}
METHODS = ("presmoothing", *RUNS)


def figures(noisy, truth, weights: dict[str, bytes]) -> dict:
    selector = weights.get("selector") or shipped_bytes("selector")
    out = {"presmoothing": score(selector_presmoothed(noisy, load_selector(selector),
                                                      BoundedNoiseConfig()), truth, 0.0)}
    for name, config in RUNS.items():
        out[name] = run_method(noisy, truth, replace(config, weights=weights))
    return {m: {"c2m_rms_mm": round(r["c2m_rms_mm"], 4),
                "normal_error_deg": round(r["normal_error_deg"], 2)} for m, r in out.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--before", required=True, help="folder of .safetensors")
    ap.add_argument("--after", default=None, help="folder of .safetensors (default: shipped)")
    ap.add_argument("--meshes", default=str(MESHES))
    ap.add_argument("--mesh", action="append", help="mesh name or file (repeatable)")
    ap.add_argument("--noise", action="append", choices=NOISE_KINDS)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    sets = {"before": weights_folder(args.before) or {},
            "after": weights_folder(args.after) or {}}
    rows = []
    for name in args.mesh or DEFAULT_MESHES:
        truth = protocol_truth(Path(args.meshes), name=name)
        for noise in args.noise or NOISE_KINDS:
            noisy = protocol_noise(truth, args.seed, noise)
            row: dict = {"mesh": name, "noise": noise}
            row.update({tag: figures(noisy, truth, weights) for tag, weights in sets.items()})
            row["after_over_before"] = {m: round(row["after"][m]["c2m_rms_mm"]
                                                 / row["before"][m]["c2m_rms_mm"], 3)
                                        for m in METHODS}
            print(json.dumps(row), file=sys.stderr, flush=True)
            rows.append(row)
    print(json.dumps({"before": args.before, "after": args.after or "shipped",
                      "seed": args.seed, "load_average": os.getloadavg(), "rows": rows},
                     indent=1))


if __name__ == "__main__":
    main()
