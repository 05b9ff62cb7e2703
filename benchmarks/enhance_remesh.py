"""What the light remesh after the update does, part by part; prints JSON.

    .venv/bin/python benchmarks/enhance_remesh.py [--mesh NAME ...]

Each mesh under the enhance benchmark's protocol (1 m high, 5 mm edges, ±1 cm noise along
normals) is enhanced by the LDM without the light remesh; then the remesh stage runs on that
result in full (one round of the isotropic kernel, then the angle clean-up: what
`remesh_iterations` 1 does), with the kernel alone, and with the clean-up alone. For each: C2M
RMS (result vertices to the truth, which depends on where the vertices lie), the reverse RMS
(truth vertices to the result surface, which does not) and the normal error, with the share of
the update's faces outside the remesh stage's angle criteria, and of each result's. Last, what
the enhance stage keeps (`light_remesh`: the full remesh, or the clean-up alone where the
kernel adds faces outside the criteria, or leaves an input vertex more than two edges from
every vertex of its result: `kernel_lost_edges`), and what the enhancement itself gives
(`enhance_mesh`: the same light remesh started ahead, on the mesh the update moves, and
carried onto the moved mesh; `remesh_ahead`).
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from enhance import bunny_protocol, score  # noqa: E402

from pipeline.enhance import EnhanceConfig, enhance_mesh  # noqa: E402
from pipeline.enhance.enhancement import light_remesh  # noqa: E402
from pipeline.geometry.mesh import TriangleMesh, mean_edge_length_m  # noqa: E402
from pipeline.reconstruct.remesh.isotropic import (  # noqa: E402
    RemeshConfig,
    angle_stats,
    remesh,
    surface_lost_edges,
)

DEFAULT_MESHES = ("stanford-bunny", "spot", "fandisk", "teapot", "cow", "cheburashka", "homer",
                  "rocker-arm", "suzanne", "beetle")


def scores(mesh: TriangleMesh, truth: TriangleMesh, config: RemeshConfig) -> dict:
    """`enhance.py`'s scores (C2M, reverse, normal error), with the vertex count and the
    shares of faces outside the angle criteria."""
    return {**score(mesh, truth, 0.0), "vertices": mesh.vertex_count,
            "angles": angle_stats(mesh.vertices_m, mesh.faces, config)}


def mesh_report(meshes: Path, name: str) -> dict:
    truth, noisy = bunny_protocol(meshes, 0, name=name)
    updated = enhance_mesh(noisy, EnhanceConfig(method="ldm", remesh_iterations=0))
    full = RemeshConfig(target_edge_length_m=mean_edge_length_m(updated), iterations=1,
                        min_component_share=0.0)
    out = {"no_remesh": scores(updated, truth, full)}
    for label, config in (("full", full), ("kernel_only", replace(full, cleanup_passes=0)),
                          ("cleanup_only", replace(full, iterations=0))):
        result = remesh(updated, config)[0]
        out[label] = scores(result, truth, full)
        if label == "kernel_only":
            out[label]["kernel_lost_edges"] = surface_lost_edges(
                updated.vertices_m, result.vertices_m, full.target_edge_length_m)
    out["light_remesh"] = scores(light_remesh(updated, 1), truth, full)
    out["enhance_mesh"] = scores(enhance_mesh(noisy, EnhanceConfig(method="ldm")), truth, full)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--meshes", default=str(ROOT.parent / "shared" / "data" / "meshes"))
    ap.add_argument("--mesh", action="append", help=f"protocol meshes (default: {DEFAULT_MESHES})")
    args = ap.parse_args()
    report = {}
    for name in args.mesh or DEFAULT_MESHES:
        report[name] = mesh_report(Path(args.meshes), name)
        brief = {k: round(v["c2m_rms_mm"], 4) for k, v in report[name].items()}
        print(name, json.dumps(brief), file=sys.stderr, flush=True)
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
