"""The `align` stage against the truth: how far each camera's surface ends from where it
belongs; prints JSON.

    .venv/bin/python benchmarks/align.py [--mesh NAME] [--seeds N]

Synthetic captures of a validation mesh (default: spot) by two rigs (`RIGS`): 4 cameras and a
subject 1 m tall, whose overlaps are thin strips, and 8 cameras and 1.8 m. The Azure Kinect
noise model, with four kinds of rig error (`ERRORS`): none (a well-calibrated rig), the
per-camera range offsets alone (2 mm standard deviation), the pose errors alone (every
written pose off by 0.1 degrees and 1 mm), both. Each camera's filtered depth is placed in the
world with the poses and offsets that `align` finds, as shipped (`AlignConfig()`), with range
offsets only, and with the stage off, and compared with where the same pixels belong (the
true pose and offset): the RMS distance over the camera's pixels, mm, averaged over the
cameras and the seeds. Beside it, how often the held-out overlaps showed pose touch-ups.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from enhance_protocol import MESHES, protocol_mesh_file  # noqa: E402

from pipeline.capture import View  # noqa: E402
from pipeline.io.mesh_io import read_mesh  # noqa: E402
from pipeline.reconstruct.align import AlignConfig, DepthView, estimate_corrections  # noqa: E402
from pipeline.reconstruct.depth_filter import DepthFilterConfig, filter_depth  # noqa: E402
from pipeline.reconstruct.registration import camera_points_image, ray_image  # noqa: E402
from pipeline.synth.noise import KinectNoiseConfig  # noqa: E402
from pipeline.synth.scene import (  # noqa: E402
    SynthConfig,
    camera_depth_biases_m,
    synthesize,
    true_cameras,
)


@dataclass(frozen=True)
class Rig:
    cameras: int
    subject_height_m: float


RIGS = {"4 cameras, 1.0 m": Rig(4, 1.0), "8 cameras, 1.8 m": Rig(8, 1.8)}
ERRORS = {"none": (False, False), "range offsets": (True, False),
          "pose errors": (False, True), "both": (True, True)}
"""Which errors the capture has: (range offsets, pose errors)."""
POSE_ERROR_DEG, POSE_ERROR_M = 0.1, 0.001
VARIANTS = {"as shipped": AlignConfig(), "offsets only": AlignConfig(poses=False),
            "off": AlignConfig(offsets=False, poses=False)}


def surface_error_mm(view: DepthView, world_from_depth: np.ndarray, offset_m: float,
                     true_world_from_depth: np.ndarray, true_offset_m: float) -> float:
    """RMS distance between where the view's pixels land with (pose, offset) and with the
    true ones, mm."""
    rays = ray_image(view.intrinsics)
    valid = view.depth_m > 0
    points = camera_points_image(view.depth_m, rays)[valid].astype(np.float64)
    unit = (rays / np.linalg.norm(rays, axis=2, keepdims=True))[valid]

    def world(pose: np.ndarray, offset: float) -> np.ndarray:
        return (points - offset * unit) @ pose[:3, :3].T + pose[:3, 3]

    apart = world(world_from_depth, offset_m) - world(true_world_from_depth, true_offset_m)
    return float(np.sqrt(np.mean(np.sum(apart**2, axis=1))) * 1e3)


def capture_row(mesh_file: Path, rig: Rig, offsets: bool, poses: bool, seed: int
                ) -> dict[str, Any]:
    noise = KinectNoiseConfig() if offsets else KinectNoiseConfig(bias_std_m=0.0)
    config = SynthConfig(model_height_m=rig.subject_height_m, seed=seed,
                         camera_count=rig.cameras, with_color=False, noise_model=noise,
                         pose_error_rot_deg=POSE_ERROR_DEG if poses else 0.0,
                         pose_error_trans_m=POSE_ERROR_M if poses else 0.0)
    _, views, truth = synthesize(read_mesh(mesh_file), config)
    true_poses = [np.asarray(c.world_from_depth) for c in true_cameras(truth, config)]
    true_offsets = camera_depth_biases_m(config, rig.cameras)
    depth_views = [_filtered(view) for view in views]
    row: dict[str, Any] = {}
    for name, align_config in VARIANTS.items():
        found = estimate_corrections(depth_views, align_config)
        errors = [surface_error_mm(v, pose, offset, true_pose, true_offset)
                  for v, pose, offset, true_pose, true_offset
                  in zip(depth_views, found.world_from_depth, found.offsets_m, true_poses,
                         true_offsets, strict=True)]
        row[name] = {"surface_error_mm": float(np.mean(errors)),
                     "poses_shown": found.poses_shown}
    return row


def _filtered(view: View) -> DepthView:
    cam = view.camera
    assert cam.world_from_depth is not None
    depth = filter_depth(view.depth_m, cam.depth_intrinsics.fx, DepthFilterConfig())
    return DepthView(depth, cam.depth_intrinsics, np.asarray(cam.world_from_depth))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--meshes", type=Path, default=MESHES)
    parser.add_argument("--mesh", default="spot")
    parser.add_argument("--seeds", type=int, default=4)
    args = parser.parse_args()
    mesh_file = protocol_mesh_file(args.meshes, args.mesh)
    results: dict[str, Any] = {}
    for rig_name, rig in RIGS.items():
        for error_name, (offsets, poses) in ERRORS.items():
            rows = [capture_row(mesh_file, rig, offsets, poses, seed)
                    for seed in range(args.seeds)]
            summary = {name: {
                "surface_error_mm": round(float(np.mean(
                    [r[name]["surface_error_mm"] for r in rows])), 3),
                "poses_shown": sum(bool(r[name]["poses_shown"]) for r in rows)}
                for name in VARIANTS}
            print(json.dumps({"rig": rig_name, "errors": error_name, **summary}),
                  file=sys.stderr, flush=True)
            results.setdefault(rig_name, {})[error_name] = summary
    print(json.dumps({"mesh": args.mesh, "seeds": args.seeds, "load_average": os.getloadavg(),
                      "pose_error": {"deg": POSE_ERROR_DEG, "m": POSE_ERROR_M},
                      "results": results}, indent=1))


if __name__ == "__main__":
    main()
