"""How much of the networks' depth correction the mesh update should follow
(`EnhanceConfig.correction_gain`), measured on meshes under the enhance benchmark's protocol.

    .venv/bin/python benchmarks/enhance_gain.py [--mesh spot --mesh fandisk] [--weights DIR]

`enhance_mesh` per mesh, method and fixed gain (`learned_gain` off), and with the learned
vertex gains (`learned`), without the light remesh so only the gain differs between runs of a
method (the networks are deterministic). Choose the gain on validation
meshes (spot, fandisk), never on the bunny, the test model.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from enhance import _weights, bunny_protocol  # noqa: E402

from pipeline.enhance import EnhanceConfig, enhance_mesh  # noqa: E402
from pipeline.enhance.metrics import c2m_summary  # noqa: E402


def sweep(name: str, meshes: Path, gains: list[float], views: int, weights: dict | None) -> dict:
    truth, noisy = bunny_protocol(meshes, 0, name=name)
    out: dict = {}
    for method in ("ldm", "regressor"):
        out[method] = {}
        for gain in gains:
            config = EnhanceConfig(method=method, views=views, correction_gain=gain,
                                   learned_gain=False, remesh_iterations=0, weights=weights)
            out[method][str(gain)] = c2m_summary(enhance_mesh(noisy, config), truth)
        config = EnhanceConfig(method=method, views=views, remesh_iterations=0, weights=weights)
        out[method]["learned"] = c2m_summary(enhance_mesh(noisy, config), truth)
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--meshes", default=str(ROOT.parent / "shared" / "data" / "meshes"))
    ap.add_argument("--mesh", action="append", help="protocol meshes (default: spot, fandisk)")
    ap.add_argument("--gains", default="0.2,0.35,0.5,0.6,0.85,1.0")
    ap.add_argument("--views", type=int, default=6)
    ap.add_argument("--weights", default=None, help="folder of .safetensors (default: shipped)")
    args = ap.parse_args()
    gains = [float(g) for g in args.gains.split(",")]
    weights = _weights(args.weights)
    report = {name: sweep(name, Path(args.meshes), gains, args.views, weights)
              for name in args.mesh or ["spot", "fandisk"]}
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
