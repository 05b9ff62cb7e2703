"""Reconstruction figures: `volumesh reconstruct --no-enhance` against Open3D's TSDF fusion.

Usage: .venv/bin/python benchmarks/reconstruct.py [--mesh PATH] [--seed N] [--cpus 2]
       [--tsdf-voxels-mm 2,3,4] [--keep DIR]

Synthesises an 8-camera 640x576 capture of the mesh (default: the Stanford bunny from
../shared/data/meshes, else the built-in subject) scaled to 1.8 m with the Azure Kinect noise
model, then runs, each as a child process pinned to --cpus cores:
  * `volumesh reconstruct CAPTURE --out mesh.glb --no-enhance` (end to end: start-up, reading,
    every stage, Draco export), and
  * Open3D's TSDF fusion (`open3d.t.geometry.VoxelBlockGrid`, raw depth, weight threshold 1)
    of the same capture at each voxel size,
measuring wall time, CPU time and peak memory (resident set of the process tree, sampled),
and the accuracy of each result against the ground truth: cloud-to-mesh distances both ways
and the share of the ground-truth surface that some camera sees lying within 5 mm of the
result. Prints one JSON object; ratios compare volumesh with TSDF at its best voxel size
(lowest C2M RMS).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

BUNNY = ROOT.parent / "shared" / "data" / "meshes" / "stanford-bunny.obj"
BLOCK_COUNT = 20_000
"""Initial hash-map capacity of the TSDF grid (16^3-voxel blocks); it grows when needed."""
TARGETS = {"c2m_rms_m": 0.0015, "coverage_visible": 0.95, "wall_s": 15.0, "peak_rss_mb": 4096}


# ----------------------------------------------------------------------------- measuring

def _tree_rss_kb(pid: int) -> int:
    """Resident memory of a process and all its descendants, KiB (0 once gone)."""
    total, stack = 0, [pid]
    while stack:
        current = stack.pop()
        try:
            status = Path(f"/proc/{current}/status").read_text()
            total += next(int(line.split()[1]) for line in status.splitlines()
                          if line.startswith("VmRSS:"))
            for task in Path(f"/proc/{current}/task").iterdir():
                stack += [int(c) for c in (task / "children").read_text().split()]
        except (OSError, StopIteration, ValueError):
            continue
    return total


def run_measured(command: list[str], cpus: int) -> dict[str, Any]:
    """Run a child pinned to `cpus` cores; wall and CPU seconds, peak tree memory, output."""
    allowed = sorted(os.sched_getaffinity(0))[:cpus]

    def pin() -> None:
        os.sched_setaffinity(0, allowed)

    started = time.perf_counter()
    child = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             preexec_fn=pin)
    peak = [0]
    done = threading.Event()

    def sample() -> None:
        while not done.is_set():
            peak[0] = max(peak[0], _tree_rss_kb(child.pid))
            done.wait(0.02)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    stdout, stderr = child.communicate()
    wall = time.perf_counter() - started
    done.set()
    sampler.join()
    usage = _child_usage(child.pid)
    if child.returncode != 0:
        raise RuntimeError(f"{command[3:5]} failed ({child.returncode}): {stderr.decode()[-2000:]}")
    return {"wall_s": round(wall, 2), "cpu_s": round(usage, 2),
            "peak_rss_mb": round(peak[0] / 1024, 1), "cpus": len(allowed),
            "stdout": stdout.decode().strip()}


_CPU_BEFORE: dict[str, float] = {}


def _child_usage(pid: int) -> float:
    """CPU seconds (user + system) of the children reaped since the last call."""
    import resource

    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    total = usage.ru_utime + usage.ru_stime
    spent = total - _CPU_BEFORE.get("children", 0.0)
    _CPU_BEFORE["children"] = total
    return spent


# ----------------------------------------------------------------------------- TSDF child

def tsdf_worker(capture: Path, voxel_m: float, out: Path) -> None:
    """Open3D's TSDF fusion of every camera's raw depth at frame 0; writes a .ply."""
    import open3d as o3d
    import open3d.core as o3c

    from pipeline.geometry.mesh import TriangleMesh
    from pipeline.io.capture_io import open_capture
    from pipeline.io.mesh_io import write_ply

    with open_capture(capture) as reader:
        views = reader.read_frame(reader.meta.frame_indices[0], with_color=False)
        scale = 1.0 / reader.meta.depth_scale
    grid = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight"), attr_dtypes=(o3c.float32, o3c.float32),
        attr_channels=(o3c.SizeVector([1]), o3c.SizeVector([1])), voxel_size=voxel_m,
        block_resolution=16, block_count=BLOCK_COUNT, device=o3c.Device("CPU:0"))
    for view in views:
        assert view.camera.world_from_depth is not None
        intrinsic = o3c.Tensor.from_numpy(view.camera.depth_intrinsics.matrix())
        extrinsic = o3c.Tensor.from_numpy(np.linalg.inv(view.camera.world_from_depth))
        units = np.round(view.depth_m * scale).astype(np.uint16)
        depth = o3d.t.geometry.Image(o3c.Tensor.from_numpy(units))
        blocks = grid.compute_unique_block_coordinates(depth, intrinsic, extrinsic, scale, 5.0)
        grid.integrate(blocks, depth, intrinsic, extrinsic, scale, 5.0)
    mesh = grid.extract_triangle_mesh(weight_threshold=1.0).to_legacy()
    write_ply(out, TriangleMesh(np.asarray(mesh.vertices),
                                np.asarray(mesh.triangles, dtype=np.int32)))


# ----------------------------------------------------------------------------- main

def synthesise(mesh_path: Path | None, seed: int, out: Path) -> dict[str, Any]:
    from pipeline.io.capture_io import write_capture
    from pipeline.io.mesh_io import read_mesh, write_ply
    from pipeline.synth.scene import SynthConfig, sample_mesh, synthesize_stream

    source = read_mesh(mesh_path) if mesh_path is not None else sample_mesh()
    config = SynthConfig(model_height_m=1.8, seed=seed)
    meta, views, truth = synthesize_stream(source, config)
    write_capture(out / "capture", meta, views)
    write_ply(out / "ground_truth.ply", truth)
    cam = meta.cameras[0].depth_intrinsics
    return {"mesh": str(mesh_path) if mesh_path else "built-in subject",
            "cameras": len(meta.cameras), "width": cam.width, "height": cam.height,
            "model_height_m": 1.8, "seed": seed, "noise": "Azure Kinect model (synth default)"}


def accuracy(result: Any, folder: Path) -> dict[str, Any]:
    from pipeline.io.capture_io import open_capture
    from pipeline.io.mesh_io import read_mesh
    from pipeline.reconstruct.quality import MetricsConfig, compare

    truth = read_mesh(folder / "ground_truth.ply")
    with open_capture(folder / "capture") as reader:
        cameras = list(reader.meta.cameras)
    return compare(result, truth, cameras, MetricsConfig())


def _summary(figures: dict[str, Any]) -> dict[str, float]:
    return {"c2m_rms_mm": round(figures["result_to_gt"]["rms_m"] * 1e3, 3),
            "c2m_mean_mm": round(figures["result_to_gt"]["mean_m"] * 1e3, 3),
            "c2m_p95_mm": round(figures["result_to_gt"]["p95_m"] * 1e3, 3),
            "gt_to_result_p95_mm": round(figures["gt_to_result"]["p95_m"] * 1e3, 3),
            "coverage_visible": round(figures["coverage_visible"], 4),
            "normal_error_mean_deg": round(figures["normal_error_deg"]["mean"], 2)}


def run_volumesh(folder: Path, cpus: int) -> dict[str, Any]:
    from pipeline.io.gltf_read import decode_glb

    out, report = folder / "volumesh.glb", folder / "report.json"
    measured = run_measured([sys.executable, "-c", "from app.cli import main; main()",
                             "reconstruct", str(folder / "capture"), "--out", str(out),
                             "--report", str(report), "--no-enhance"], cpus)
    figures = accuracy(decode_glb(out.read_bytes()), folder)
    stages = json.loads(report.read_text())
    measured.pop("stdout")
    return {**measured, "triangles": stages["triangles"], "glb_bytes": out.stat().st_size,
            "stage_seconds": stages["stage_seconds"],
            "depth_offset_mm": stages["stage_stats"]["align"]["depth_offset_mm"],
            "remesh_warning": stages["stage_stats"]["remesh"]["warning"],
            **_summary(figures), "accuracy": figures}


def run_tsdf(folder: Path, voxel_mm: float, cpus: int) -> dict[str, Any]:
    from pipeline.io.mesh_io import read_mesh

    out = folder / f"tsdf_{voxel_mm:g}mm.ply"
    measured = run_measured([sys.executable, str(Path(__file__).resolve()), "--tsdf-worker",
                             str(folder / "capture"), str(voxel_mm / 1000), str(out)], cpus)
    result = read_mesh(out)
    measured.pop("stdout")
    return {"voxel_mm": voxel_mm, **measured, "triangles": result.face_count,
            **_summary(accuracy(result, folder))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mesh", type=Path, default=BUNNY if BUNNY.is_file() else None)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cpus", type=int, default=2, help="cores each run is pinned to")
    parser.add_argument("--tsdf-voxels-mm", default="2,3,4")
    parser.add_argument("--keep", type=Path, help="keep the capture and results here")
    parser.add_argument("--tsdf-worker", nargs=3, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.tsdf_worker:
        capture, voxel, out = args.tsdf_worker
        tsdf_worker(Path(capture), float(voxel), Path(out))
        return
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.keep or Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        load_before = os.getloadavg()[0]
        capture = synthesise(args.mesh, args.seed, folder)
        _child_usage(0)  # reset the children's CPU account
        ours = run_volumesh(folder, args.cpus)
        tsdf = [run_tsdf(folder, float(v), args.cpus) for v in args.tsdf_voxels_mm.split(",")]
        load_after = os.getloadavg()[0]
    best = min(tsdf, key=lambda r: r["c2m_rms_mm"])
    print(json.dumps({
        "capture": capture,
        "command": "volumesh reconstruct CAPTURE --out volumesh.glb --report report.json "
                   "--no-enhance",
        "volumesh": {k: v for k, v in ours.items() if k != "accuracy"},
        "volumesh_accuracy": ours["accuracy"],
        "tsdf": tsdf,
        "tsdf_best_voxel_mm": best["voxel_mm"],
        "ratios_volumesh_to_best_tsdf": {
            "wall_time": round(ours["wall_s"] / best["wall_s"], 2),
            "cpu_time": round(ours["cpu_s"] / best["cpu_s"], 2),
            "peak_memory": round(ours["peak_rss_mb"] / best["peak_rss_mb"], 2),
            "c2m_rms": round(ours["c2m_rms_mm"] / best["c2m_rms_mm"], 3),
            "coverage_visible": round(ours["coverage_visible"] / best["coverage_visible"], 3),
        },
        "targets": {
            "c2m_rms_le_1.5mm": ours["c2m_rms_mm"] <= TARGETS["c2m_rms_m"] * 1e3,
            "coverage_ge_95pct": ours["coverage_visible"] >= TARGETS["coverage_visible"],
            "better_than_best_tsdf": bool(ours["c2m_rms_mm"] < best["c2m_rms_mm"]
                                          and ours["coverage_visible"]
                                          > best["coverage_visible"]),
            "wall_le_15s": ours["wall_s"] <= TARGETS["wall_s"],
            "peak_le_4GB": ours["peak_rss_mb"] <= TARGETS["peak_rss_mb"],
        },
        "machine": {"cpus_visible": os.cpu_count(), "cpus_per_run": ours["cpus"],
                    "load_average_1min": [round(load_before, 2), round(load_after, 2)]},
    }, indent=2))


if __name__ == "__main__":
    main()
