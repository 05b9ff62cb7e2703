"""Real depth against itself: volumesh and Open3D's TSDF on five real Kinect frames.

Usage: .venv/bin/python benchmarks/real_room.py [--room DIR] [--tsdf-voxels-mm 10,20]
       [--pixel-step 1] [--keep DIR]

The frames of ../shared/data/real/kinect-room-5-frames (a room, far wall at 4-5 m; no ground
truth) are written as a 5-camera capture (`pipeline.io.posed_frames`) and reconstructed by
`volumesh reconstruct`'s stages in this process, with the `align` stage on (the default) and
off, and fused by Open3D's TSDF (`VoxelBlockGrid`, raw depth up to 5.5 m, truncation 8 voxels,
surfaces seen by one frame kept) at each voxel size.
Each mesh is measured against every frame's raw depth within 0.25-5.5 m, posed as the capture
says (`pipeline.reconstruct.quality.depth_agreement`): per frame, the median distance of its
points to the mesh; per depth band (all frames pooled), the share of points within 5 cm.
Prints one JSON object; `targets` checks the median (<= 5 mm for every frame) and the share
(>= 90 % within 5 cm in every band up to 5.5 m).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pipeline.capture import CameraInfo  # noqa: E402
from pipeline.geometry.mesh import TriangleMesh  # noqa: E402
from pipeline.io.capture_io import open_capture  # noqa: E402
from pipeline.io.posed_frames import write_posed_frames_capture  # noqa: E402
from pipeline.reconstruct.quality import DepthAgreementConfig, depth_agreement  # noqa: E402
from pipeline.stage_config import config_from_options  # noqa: E402
from pipeline.stages import reconstruct  # noqa: E402

ROOM = ROOT.parent / "shared" / "data" / "real" / "kinect-room-5-frames"
TARGET_MEDIAN_MM = 5.0
TARGET_WITHIN_5CM = 0.90
ALIGN_OFF = {"align": {"offsets": False, "poses": False}}
MAX_DEPTH_M = 5.5


def raw_views(capture: Path) -> list[tuple[CameraInfo, Any]]:
    """Each camera with its raw depth, posed as the capture says."""
    with open_capture(capture) as reader:
        frame = reader.meta.frame_indices[0]
        return [(view.camera, view.depth_m)
                for view in reader.read_frame(frame, with_color=False)]


def run_volumesh(capture: Path, options: dict[str, Any]) -> tuple[TriangleMesh, dict[str, Any]]:
    """The reconstruction (every stage but the enhancement), with its timing and figures."""
    config = config_from_options({"enhance": False, **options})
    started = time.perf_counter()
    with open_capture(capture) as reader:
        mesh, report = reconstruct(reader, config)
    stats = report["stage_stats"]
    return mesh, {"wall_s": round(time.perf_counter() - started, 1),
                  "stage_seconds": report["stage_seconds"], "triangles": mesh.face_count,
                  "align": stats.get("align"), "register": stats.get("register")}


def run_tsdf(capture: Path, voxel_m: float) -> tuple[TriangleMesh, dict[str, Any]]:
    """Open3D's TSDF fusion of every camera's raw depth (truncation 8 voxels)."""
    import open3d as o3d
    import open3d.core as o3c

    started = time.perf_counter()
    views = raw_views(capture)
    grid = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight"), attr_dtypes=(o3c.float32, o3c.float32),
        attr_channels=(o3c.SizeVector([1]), o3c.SizeVector([1])), voxel_size=voxel_m,
        block_resolution=16, block_count=40_000, device=o3c.Device("CPU:0"))
    for camera, depth_m in views:
        assert camera.world_from_depth is not None
        intrinsic = o3c.Tensor.from_numpy(camera.depth_intrinsics.matrix())
        extrinsic = o3c.Tensor.from_numpy(np.linalg.inv(camera.world_from_depth))
        depth = o3d.t.geometry.Image(o3c.Tensor.from_numpy(
            np.round(depth_m * 1000.0).astype(np.uint16)))
        blocks = grid.compute_unique_block_coordinates(depth, intrinsic, extrinsic, 1000.0,
                                                       MAX_DEPTH_M)
        grid.integrate(blocks, depth, intrinsic, extrinsic, 1000.0, MAX_DEPTH_M)
    # Below one observation's weight: a surface one frame saw is kept (most of a room is
    # seen by one or two frames).
    legacy = grid.extract_triangle_mesh(weight_threshold=0.5).to_legacy()
    mesh = TriangleMesh(np.asarray(legacy.vertices, dtype=np.float64),
                        np.asarray(legacy.triangles, dtype=np.int32))
    return mesh, {"voxel_mm": round(voxel_m * 1e3, 1),
                  "wall_s": round(time.perf_counter() - started, 1),
                  "triangles": mesh.face_count}


def measured(mesh: TriangleMesh, views: list[tuple[CameraInfo, Any]], pixel_step: int
             ) -> dict[str, Any]:
    figures = depth_agreement(mesh, views, DepthAgreementConfig(pixel_step=pixel_step))
    cameras, bands = figures["cameras"], figures["bands_m"]
    return {"median_mm": {cid: f["median_mm"] for cid, f in cameras.items()},
            "within_5cm_by_band_m": {band: f["within_near"] for band, f in bands.items()},
            "points_by_band_m": {band: f["points"] for band, f in bands.items()}}


def targets(figures: dict[str, Any]) -> dict[str, bool]:
    shares = [s for s in figures["within_5cm_by_band_m"].values() if s is not None]
    return {"median_le_5mm_every_frame": all(m <= TARGET_MEDIAN_MM
                                             for m in figures["median_mm"].values()),
            "within_5cm_ge_90pct_every_band": all(s >= TARGET_WITHIN_5CM for s in shares)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--room", type=Path, default=ROOM)
    parser.add_argument("--tsdf-voxels-mm", default="10,20")
    parser.add_argument("--pixel-step", type=int, default=1,
                        help="measure every this many pixels of each frame")
    parser.add_argument("--keep", type=Path, help="keep the capture and meshes here")
    args = parser.parse_args()
    if not (args.room / "pose.txt").is_file():
        raise SystemExit(f"{args.room}: no pose.txt (the shared real data are absent)")
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.keep or Path(tmp)
        capture = folder / "capture"
        write_posed_frames_capture(args.room, capture)
        views = raw_views(capture)
        results: dict[str, Any] = {}
        for name, options in (("volumesh", {}), ("volumesh_align_off", ALIGN_OFF)):
            mesh, info = run_volumesh(capture, options)
            results[name] = {**info, **measured(mesh, views, args.pixel_step)}
            results[name]["targets"] = targets(results[name])
            if args.keep:
                from pipeline.io.mesh_io import write_ply

                write_ply(folder / f"{name}.ply", mesh)
        results["tsdf"] = []
        for voxel_mm in (float(v) for v in args.tsdf_voxels_mm.split(",")):
            mesh, info = run_tsdf(capture, voxel_mm / 1000.0)
            results["tsdf"].append({**info, **measured(mesh, views, args.pixel_step)})
    print(json.dumps({
        "data": str(args.room), "cameras": len(views), "pixel_step": args.pixel_step,
        **results,
        "machine": {"cpus_visible": os.cpu_count(),
                    "load_average_1min": [round(load_before, 2), round(os.getloadavg()[0], 2)]},
    }, indent=1))


if __name__ == "__main__":
    main()
