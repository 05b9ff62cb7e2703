"""Calibration figures: camera pose errors and run time on synthetic ChArUco captures.

Usage: .venv/bin/python benchmarks/calibration.py [--kinds plane,cube] [--frames 30]
       [--seeds 0,1,2] [--cameras 8] [--icp] [--workdir DIR]
Each run renders a synthetic calibration capture (the 8-camera Azure Kinect rig, Kinect-like
colour cameras with lens distortion, image noise and blur, depth noise), writes it in capture
format v1, calibrates it from disk as `volumesh calibrate` does and compares the poses with the
truth after a rigid fit over the camera centres. Prints one JSON object; `targets` says whether
the calibration's targets are met (median rotation <= 0.05 deg, median translation <= 1 mm,
max translation <= 3 mm, <= 60 s for 8 cameras x 30 frames).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.calibration import CalibrationConfig, calibrate  # noqa: E402
from pipeline.calibration.evaluate import pose_errors  # noqa: E402
from pipeline.io.capture_io import open_capture, write_capture  # noqa: E402
from pipeline.synth.target import TargetSynthConfig, synthesize_calibration  # noqa: E402


def run_once(kind: str, frames: int, seed: int, cameras: int, icp: bool, workdir: Path
             ) -> dict[str, Any]:
    capture_dir = workdir / f"{kind}_{frames}_{seed}"
    started = time.perf_counter()
    meta, views, truth = synthesize_calibration(TargetSynthConfig(
        kind=kind, frame_count=frames, camera_count=cameras, seed=seed))
    write_capture(capture_dir, meta, views)
    synth_s = time.perf_counter() - started
    started = time.perf_counter()
    with open_capture(capture_dir) as reader:
        world_from_depth, report = calibrate(reader, CalibrationConfig(icp=icp, seed=seed))
    calibrate_s = time.perf_counter() - started
    shutil.rmtree(capture_dir)
    errors = pose_errors(world_from_depth, truth)
    return {
        "kind": kind, "frames": frames, "seed": seed, "cameras": cameras, "icp": icp,
        "calibrate_s": round(calibrate_s, 2), "synth_s": round(synth_s, 2),
        "rotation_deg_median": errors["rotation_deg_median"],
        "rotation_deg_max": errors["rotation_deg_max"],
        "translation_mm_median": errors["translation_mm_median"],
        "translation_mm_max": errors["translation_mm_max"],
        "reprojection_rms_px": report["reprojection_rms_px_all"],
        "triangulation_error_mm_median": report["triangulation_error_mm"].get("median"),
        "views_used": sum(report["views_used"].values()),
        "rejected_views": len(report["rejected_views"]),
        "warnings": len(report["warnings"]),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--kinds", default="plane,cube")
    parser.add_argument("--frames", default="30", help="comma-separated frame counts")
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--cameras", type=int, default=8)
    parser.add_argument("--icp", action="store_true", help="also refine by depth ICP")
    parser.add_argument("--workdir", type=Path, default=None)
    args = parser.parse_args()
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="volumesh-calib-bench-"))
    runs = [run_once(kind, int(frames), int(seed), args.cameras, args.icp, workdir)
            for kind in args.kinds.split(",") for frames in args.frames.split(",")
            for seed in args.seeds.split(",")]
    if args.workdir is None:
        shutil.rmtree(workdir, ignore_errors=True)
    worst = {key: max(r[key] for r in runs) for key in
             ("rotation_deg_median", "translation_mm_median", "translation_mm_max",
              "calibrate_s")}
    timed = [r["calibrate_s"] for r in runs if r["cameras"] == 8 and r["frames"] == 30]
    print(json.dumps({
        "benchmark": "calibration",
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
        "runs": runs,
        "worst": worst,
        "targets": {
            "rotation_deg_median_le_0.05": worst["rotation_deg_median"] <= 0.05,
            "translation_mm_median_le_1": worst["translation_mm_median"] <= 1.0,
            "translation_mm_max_le_3": worst["translation_mm_max"] <= 3.0,
            "calibrate_8x30_le_60s": bool(timed) and max(timed) <= 60.0,
        },
    }, indent=1))


if __name__ == "__main__":
    main()
