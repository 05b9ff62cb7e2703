"""The light remesh's angle clean-up on a patch around the faces outside the criteria
(`enforce_angles`, as the pipeline runs it) against its passes over the whole mesh, which the
patch is held equal to; prints JSON.

    .venv/bin/python benchmarks/angle_cleanup.py [--mesh NAME] [--repeats N]

The input is what the clean-up gets in `enhance_mesh`: the light remesh's kernel result on the
LDM's update of a protocol mesh (`bunny_protocol`, the LDM at 4 steps with no remesh, then
`remesh` with no clean-up passes). Both ways run `repeats` times, alternating, in this
process; the figures are min and median milliseconds, and `same` says whether the two meshes
and their angles are equal bit for bit.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from enhance import bunny_protocol  # noqa: E402
from remesh_speed import light_remesh_config  # noqa: E402

from pipeline.enhance import EnhanceConfig, enhance_mesh  # noqa: E402
from pipeline.geometry.order import reordered, spatial_order  # noqa: E402
from pipeline.geometry.repair import compact, triangle_angles_deg  # noqa: E402
from pipeline.reconstruct.remesh import angle_cleanup  # noqa: E402
from pipeline.reconstruct.remesh.isotropic import remesh  # noqa: E402


def whole_mesh(vertices_m, faces, angles, min_deg: float, max_deg: float, passes: int):
    """The clean-up's passes over the whole mesh, then the compaction."""
    done = angle_cleanup._passes(vertices_m, faces, angles, min_deg, max_deg, passes, None)
    assert done is not None  # a whole mesh has no rim
    out_v, out_f = compact(done[0], done[1])
    return out_v, out_f, done[2], done[4]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--meshes", default=str(ROOT.parent / "shared" / "data" / "meshes"))
    ap.add_argument("--mesh", default="stanford-bunny")
    ap.add_argument("--repeats", type=int, default=20)
    args = ap.parse_args()

    _, noisy = bunny_protocol(Path(args.meshes), 0, name=args.mesh)
    update = enhance_mesh(noisy, EnhanceConfig(method="ldm", remesh_iterations=0))
    update = reordered(update, spatial_order(update))
    config = light_remesh_config(update, None)
    kernel_result = remesh(update, replace(config, cleanup_passes=0))[0]
    v, f = kernel_result.vertices_m, kernel_result.faces
    angles = triangle_angles_deg(v, f)
    cleanup = (angles, config.min_angle_deg, config.max_angle_deg, config.cleanup_passes)
    ways = {"patch": angle_cleanup.enforce_angles, "whole_mesh": whole_mesh}
    results = {name: way(v, f, *cleanup) for name, way in ways.items()}  # warm-up
    seconds: dict[str, list[float]] = {name: [] for name in ways}
    for _ in range(args.repeats):
        for name, way in ways.items():
            start = time.perf_counter()
            way(v, f, *cleanup)
            seconds[name].append(time.perf_counter() - start)
    patch, whole = results["patch"], results["whole_mesh"]
    print(json.dumps({
        "mesh": args.mesh, "faces": len(f), "cores": len(os.sched_getaffinity(0)),
        "outside_criteria": int(angle_cleanup._outside(angles, *cleanup[1:3]).sum()),
        "operations": patch[3],
        "ms": {name: {"min": round(1e3 * min(s), 1), "median": round(1e3 * np.median(s), 1)}
               for name, s in seconds.items()},
        "same": all(np.array_equal(a, b) for a, b in zip(patch[:3], whole[:3], strict=True))
        and patch[3] == whole[3],
    }))


if __name__ == "__main__":
    main()
