"""The self-check (`EnhanceConfig.self_check`) under the paper's protocol; prints JSON.

    .venv/bin/python benchmarks/enhance_self_check.py [--meshes DIR] [--mesh NAME|FILE ...]
        [--method ldm|regressor] [--seed N]

For each mesh (by default every protocol mesh in the folder, the bunny included): the
classical method (the pre-smoothing, the normal filter and the light remesh, no network), the
networks' result, and the networks' result self-checked, with what the check measured on its
simulated copy and the time of each. The check chose right where it kept the networks on a
mesh where they beat the classical method, or the classical result where they lose to it.
`--meshes` takes a folder of .obj, .ply, .off, .stl, .glb or .gltf files.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from enhance_protocol import (  # noqa: E402
    MESHES,
    bunny_protocol,
    classical,
    protocol_mesh_names,
    run_method,
    score,
)

from pipeline.enhance import EnhanceConfig, enhance_mesh  # noqa: E402
from pipeline.enhance.self_check import SelfCheck  # noqa: E402


def mesh_row(meshes: Path, name: str, method: str, seed: int = 0) -> dict:
    truth, noisy = bunny_protocol(meshes, seed, name=name)
    config = EnhanceConfig(method=method)
    classical_rms = classical(noisy, truth, config)["c2m_rms_mm"]
    networks = run_method(noisy, truth, config)
    checks: list[SelfCheck] = []
    started = time.perf_counter()
    checked = enhance_mesh(noisy, replace(config, self_check=True), on_check=checks.append)
    checked_score = score(checked, truth, time.perf_counter() - started)
    help_really = networks["c2m_rms_mm"] < classical_rms
    return {
        "vertices": truth.vertex_count,
        "classical_rms_mm": round(classical_rms, 4),
        "networks_rms_mm": round(networks["c2m_rms_mm"], 4),
        "self_checked_rms_mm": round(checked_score["c2m_rms_mm"], 4),
        "networks_gain_over_classical_pct": round(
            100 * (1 - networks["c2m_rms_mm"] / classical_rms), 2),
        "self_checked_gain_over_classical_pct": round(
            100 * (1 - checked_score["c2m_rms_mm"] / classical_rms), 2),
        "check": {k: round(v, 4) if isinstance(v, float) else v
                  for k, v in checks[0].as_stats().items()},
        "check_predicted_gain_pct": round(100 * (1 - checks[0].with_networks_rms_m
                                                 / checks[0].without_networks_rms_m), 2),
        "networks_help": help_really,
        "chose_right": checks[0].networks_help == help_really,
        "networks_seconds": round(networks["seconds"], 2),
        "self_checked_seconds": round(checked_score["seconds"], 2),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--meshes", default=str(MESHES))
    ap.add_argument("--mesh", action="append", help="a name in --meshes or a mesh file")
    ap.add_argument("--method", default="ldm", choices=("ldm", "regressor"))
    ap.add_argument("--seed", type=int, default=0, help="the protocol's noise seed")
    args = ap.parse_args()
    meshes = Path(args.meshes)
    rows: dict = {}
    for name in args.mesh or protocol_mesh_names(meshes):
        try:
            rows[name] = mesh_row(meshes, name, args.method, args.seed)
        except ValueError as exc:  # the protocol's remesher refuses the input
            rows[name] = {"error": str(exc)}
        print(name, json.dumps(rows[name]), file=sys.stderr, flush=True)
    scored = {n: r for n, r in rows.items() if "error" not in r}
    print(json.dumps({"method": args.method, "seed": args.seed, "meshes": rows, "summary": {
        "scored": len(scored),
        "chose_right": sorted(n for n, r in scored.items() if r["chose_right"]),
        "chose_wrong": sorted(n for n, r in scored.items() if not r["chose_right"]),
        "min_self_checked_gain_over_classical_pct": min(
            (r["self_checked_gain_over_classical_pct"] for r in scored.values()), default=None),
    }}, indent=1))


if __name__ == "__main__":
    main()
