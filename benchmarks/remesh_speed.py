"""The light remesh's time, its kernel in one child against spatial pieces side by side, and
the boundary split's rounds near the long edges against rounds over every face; prints JSON.

    .venv/bin/python benchmarks/remesh_speed.py [--mesh NAME] [--repeats N] [--pieces N ...]

Each variant also runs `_started_ahead`, as `enhance_mesh` runs it: the kernel's children
started a second before (`kernel.kernel_children`), while the stages before the remesh
run. The input is what `enhance_mesh` hands the light remesh: the LDM's update of a protocol
mesh (`bunny_protocol`, the LDM at 4 steps with no remesh), in a spatial order. Each variant
runs `repeats` times, alternating, in this process after one warm-up call; the C2M figures
of both remeshes against the protocol's truth say whether the pieces cost anything. Last,
the speculative remesh, started ahead of the update (the default on a GPU): its start,
and its finish `--overlap` seconds later (`ahead_seconds`).

    .venv/bin/python benchmarks/remesh_speed.py [--overlap S]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from enhance import bunny_protocol, score  # noqa: E402

from pipeline.enhance import EnhanceConfig, enhance_mesh  # noqa: E402
from pipeline.geometry.mesh import TriangleMesh, mean_edge_length_m  # noqa: E402
from pipeline.geometry.order import reordered, spatial_order  # noqa: E402
from pipeline.geometry.repair import repair  # noqa: E402
from pipeline.reconstruct.remesh.boundary_split import split_boundary_edges, split_everywhere  # noqa: E402
from pipeline.reconstruct.remesh.isotropic import RemeshConfig, kernel_piece_count, remesh  # noqa: E402
from pipeline.reconstruct.remesh.kernel import kernel_children  # noqa: E402
from pipeline.reconstruct.remesh.speculative import (  # noqa: E402
    checked_faces,
    finish_remesh_ahead,
    start_remesh_ahead,
)


def light_remesh_config(mesh: TriangleMesh, processes: int | None) -> RemeshConfig:
    """`light_remesh`'s settings, with `processes` kernel children."""
    from pipeline.enhance.clean.light_remesh import (
        LIGHT_REMESH_MAX_ADDED_OUTSIDE,
        LIGHT_REMESH_MAX_LOST_EDGES,
    )

    return RemeshConfig(target_edge_length_m=mean_edge_length_m(mesh), iterations=1,
                        max_kernel_added_outside=LIGHT_REMESH_MAX_ADDED_OUTSIDE,
                        max_kernel_lost_edges=LIGHT_REMESH_MAX_LOST_EDGES,
                        min_component_share=0.0, kernel_processes=processes)


def timed_remesh(mesh: TriangleMesh, config: RemeshConfig, ahead: bool) -> tuple[float, float]:
    """Seconds of one `remesh` and of its wait for the kernel; `ahead`: as `enhance_mesh` runs
    it, the kernel's children started a second before, while the stages before it run."""
    count = kernel_piece_count(mesh.face_count, config.kernel_processes) if ahead else 0
    with kernel_children(count) as children:
        time.sleep(1.0 if ahead else 0.0)
        start = time.perf_counter()
        wait = remesh(mesh, config, children)[1]["kernel_wait_s"]
        return round(time.perf_counter() - start, 3), round(wait, 3)


def timed_ahead(mesh: TriangleMesh, config: RemeshConfig, overlap_s: float
                ) -> tuple[float, float, float]:
    """Seconds of the speculative remesh's start and finish, and the finish's wait for the
    kernel, as `enhance_mesh` runs them on a GPU: children started a second before, the start
    on the mesh the update will move (its faces checked beforehand, beside the render:
    `checked_faces`), the finish `overlap_s` later (the networks and the update) on the moved
    mesh. Here the mesh does not move: the times do not depend on it."""
    count = kernel_piece_count(mesh.face_count, config.kernel_processes)
    checked = checked_faces(mesh)  # beside the render, in `enhance_mesh`
    with kernel_children(count) as children:
        time.sleep(1.0)
        start = time.perf_counter()
        ahead = start_remesh_ahead(mesh, config, children, checked)
        started = time.perf_counter()
        assert ahead is not None
        time.sleep(overlap_s)
        finishing = time.perf_counter()
        _, stats = finish_remesh_ahead(ahead, mesh)
        return (round(started - start, 3), round(time.perf_counter() - finishing, 3),
                round(stats["kernel_wait_s"], 3))


def timed(call, repeats: int) -> list[float]:
    out = []
    for _ in range(repeats):
        start = time.perf_counter()
        call()
        out.append(round(time.perf_counter() - start, 3))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--meshes", default=str(ROOT.parent / "shared" / "data" / "meshes"))
    ap.add_argument("--mesh", default="stanford-bunny")
    ap.add_argument("--repeats", type=int, default=4)
    ap.add_argument("--overlap", type=float, default=0.6,
                    help="seconds between the ahead remesh's start and finish (the networks "
                    "and the update on a GPU)")
    ap.add_argument("--pieces", type=int, nargs="*", default=[],
                    help="also time these piece counts (the default's is one per core)")
    args = ap.parse_args()
    truth, noisy = bunny_protocol(Path(args.meshes), 0, 0.005, name=args.mesh)
    update = enhance_mesh(noisy, EnhanceConfig(method="ldm", remesh_iterations=0))
    update = reordered(update, spatial_order(update))
    configs = {"one_child": light_remesh_config(update, 1),
               "pieces": light_remesh_config(update, None)}
    configs |= {f"pieces_{n}": light_remesh_config(update, n) for n in args.pieces}
    results = {name: remesh(update, config)[0] for name, config in configs.items()}  # warm-up
    seconds: dict[str, list[float]] = {}
    waits: dict[str, list[float]] = {}
    for _ in range(args.repeats):
        for name, config in configs.items():
            for ahead in (False, True):
                key = f"{name}_started_ahead" if ahead else name
                took, wait = timed_remesh(update, config, ahead)
                seconds.setdefault(key, []).append(took)
                waits.setdefault(key, []).append(wait)
    ahead = [timed_ahead(update, configs["pieces"], args.overlap) for _ in range(args.repeats)]
    v, f, _ = repair(update.vertices_m, update.faces, 0.0)
    edge_m = mean_edge_length_m(update)
    region, whole = split_boundary_edges(v, f, edge_m), split_everywhere(v, f, edge_m)
    print(json.dumps({
        "mesh": args.mesh, "faces": update.face_count, "cores": len(os.sched_getaffinity(0)),
        "pieces": kernel_piece_count(update.face_count, None),
        "light_remesh_seconds": seconds,
        "waiting_for_the_kernel_seconds": waits,
        "ahead_seconds": {"start": [a[0] for a in ahead], "finish": [a[1] for a in ahead],
                          "finish_waiting": [a[2] for a in ahead],
                          "finish_after_s": args.overlap},
        "c2m": {name: {k: round(x, 5) for k, x in score(mesh, truth, 0.0).items()
                       if k != "seconds"} for name, mesh in results.items()},
        "faces_out": {name: mesh.face_count for name, mesh in results.items()},
        "boundary_split_seconds": {
            "near_long_edges": timed(lambda: split_boundary_edges(v, f, edge_m), args.repeats),
            "every_face": timed(lambda: split_everywhere(v, f, edge_m), args.repeats)},
        "boundary_split_same": bool(np.array_equal(region[0], whole[0])
                                    and np.array_equal(region[1], whole[1])),
        "boundary_split_added_vertices": len(region[0]) - len(v),
    }, indent=1))


if __name__ == "__main__":
    main()
