"""How much of the networks' depth correction the mesh update should follow
(`EnhanceConfig.correction_gain`), measured on meshes under the enhance benchmark's protocol.

    .venv/bin/python benchmarks/enhance_gain.py [--mesh spot --mesh fandisk] > gain.json

The networks run once per mesh and method; each gain then scales their correction of the
pre-smoothed renders before the view update (no light remesh, so only the gain differs). Choose
the gain on validation meshes (spot, fandisk), never on the bunny, the test model.
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
sys.path.insert(0, str(ROOT / "benchmarks"))

from enhance import bunny_protocol  # noqa: E402

from pipeline.enhance import baselines  # noqa: E402
from pipeline.enhance.config import EnhanceConfig  # noqa: E402
from pipeline.enhance.inference import run_network  # noqa: E402
from pipeline.enhance.metrics import c2m_summary  # noqa: E402
from pipeline.enhance.render import make_views, render_depth, view_directions  # noqa: E402
from pipeline.enhance.update import UpdateConfig, update_vertices  # noqa: E402


def sweep(name: str, meshes: Path, gains: list[float], views: int) -> dict:
    truth, noisy = bunny_protocol(meshes, 0, name=name)
    cams = make_views(noisy.vertices_m, view_directions(views), 256)
    r_noisy = render_depth(noisy, cams)
    base = baselines.laplacian_smooth(noisy, EnhanceConfig().presmooth_iterations)
    r_base = render_depth(base, cams, with_color=False)
    update = replace(UpdateConfig(), unseen_follow_moves=True)
    out: dict = {}
    for method in ("ldm", "regressor"):
        pred = run_network(r_base, r_noisy, EnhanceConfig(method=method, views=views))
        out[method] = {}
        for gain in gains:
            depth = (r_base.depth_n + gain * (pred - r_base.depth_n)).astype(np.float32)
            moved, _ = update_vertices(base, r_base, depth, update)
            out[method][str(gain)] = c2m_summary(moved, truth)
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--meshes", default=str(ROOT.parent / "shared" / "data" / "meshes"))
    ap.add_argument("--mesh", action="append", help="protocol meshes (default: spot, fandisk)")
    ap.add_argument("--gains", default="0.2,0.35,0.5,0.6,0.85,1.0")
    ap.add_argument("--views", type=int, default=6)
    args = ap.parse_args()
    gains = [float(g) for g in args.gains.split(",")]
    report = {name: sweep(name, Path(args.meshes), gains, args.views)
              for name in args.mesh or ["spot", "fandisk"]}
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
