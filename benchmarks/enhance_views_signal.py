"""How much of the depth networks' correction is signal, per protocol mesh; prints JSON.

.venv/bin/python benchmarks/enhance_views_signal.py [--mesh NAME ...] (about a minute a mesh)

Under issue 4's protocol (`enhance.bunny_protocol`) the pre-smoothed mesh's renders are
corrected by each network (gain 1), and the correction is compared with what would put the
base on the truth:
- depth level: RMS error (mm) of the base's and the network's depth against the truth's own
  renders, where all three see one surface (within 5 mm), whole and weighted by the cosine of
  the surface to the ray (how the update weighs a view);
- per view: the least-squares gain of the view's steps along the normal onto the base's
  signed distance to the truth (1: the view's correction is all signal, 0: none of it);
- across views: the covariance of two views' steps at the vertices both see, over their
  variance (the share of a view's correction the other views repeat).
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

from pipeline.enhance import EnhanceConfig  # noqa: E402
from pipeline.enhance.enhancement import enhance_renders, update_inputs  # noqa: E402
from pipeline.enhance.metrics import signed_c2m  # noqa: E402
from pipeline.enhance.render.views import render_depth  # noqa: E402
from pipeline.enhance.update.steps import view_steps  # noqa: E402
from pipeline.geometry.order import reordered, spatial_order  # noqa: E402

SAME_SURFACE_M = 0.005


def mesh_signal(meshes: Path, name: str) -> dict:
    truth, noisy = bunny_protocol(meshes, 0, name=name)
    ordered = reordered(noisy, spatial_order(noisy))
    config = EnhanceConfig(method="ldm", steps=4)
    inputs = update_inputs(ordered, config, "cpu")
    base = inputs.base_renders
    views = base.views
    clean = render_depth(truth, views, with_color=False)
    range_m = views.depth_range_m
    same = clean.valid & base.valid & (np.abs(clean.depth_n - base.depth_n) * range_m
                                       < SAME_SURFACE_M)
    pixel_m = range_m / views.resolution
    rows, cols = np.gradient(clean.depth_n * range_m / pixel_m, axis=(1, 2))
    cos = (1.0 / np.sqrt(1.0 + rows**2 + cols**2))[same]
    base_err_mm = (base.depth_n - clean.depth_n)[same] * range_m * 1e3
    to_truth_m = -signed_c2m(inputs.base.vertices_m, truth)

    def rms(x: np.ndarray) -> float:
        return round(float(np.sqrt(np.mean(x**2))), 4)

    out: dict = {"vertices": truth.vertex_count,
                 "base_depth_rms_mm": rms(base_err_mm),
                 "base_depth_rms_cos_weighted_mm": rms(base_err_mm * cos)}
    for method in ("regressor", "ldm"):
        enhanced = enhance_renders(base, inputs.renders,
                                   replace(config, method=method, correction_gain=1.0))
        err_mm = (enhanced - clean.depth_n)[same] * range_m * 1e3
        steps = view_steps(inputs.base, base, enhanced, inputs.update)
        out[method] = {"depth_rms_mm": rms(err_mm), "depth_rms_cos_weighted_mm": rms(err_mm * cos),
                       **view_signal(steps.along_normals_m(), steps.weights > 0, to_truth_m)}
    return out


def view_signal(along_m: np.ndarray, seen: np.ndarray, to_truth_m: np.ndarray) -> dict:
    """Per view, the least-squares gain of its (K, V) steps along the normal `along_m` onto the
    (V,) move that puts each vertex on the truth, where it sees the vertex (`seen`, (K, V)); and
    the views' summed pairwise covariance over their variance at the vertices both see."""
    gains = [float(np.sum(a[s] * to_truth_m[s]) / np.sum(a[s] ** 2))
             for a, s in zip(along_m, seen, strict=True)]
    cov = var = 0.0
    for i in range(len(along_m)):
        for j in range(i + 1, len(along_m)):
            both = seen[i] & seen[j]
            a, b = along_m[i][both], along_m[j][both]
            cov += float(np.sum(a * b))
            var += 0.5 * float(np.sum(a**2) + np.sum(b**2))
    return {"per_view_signal_gain": [round(g, 3) for g in gains],
            "cross_view_share": round(cov / var, 3)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--meshes", default=str(ROOT.parent / "shared" / "data" / "meshes"))
    ap.add_argument("--mesh", action="append", help="protocol meshes (default: the bunny, "
                    "beetle, cow, spot, fandisk)")
    args = ap.parse_args()
    names = args.mesh or ["stanford-bunny", "beetle", "cow", "spot", "fandisk"]
    print(json.dumps({name: mesh_signal(Path(args.meshes), name) for name in names}, indent=1))


if __name__ == "__main__":
    main()
