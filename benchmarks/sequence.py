"""Volumetric video figures: temporal stability, per-frame accuracy, and sequence throughput.

Usage: .venv/bin/python benchmarks/sequence.py [--part stability,moving,articulated,throughput]
       [--frames-static 8] [--frames-moving 6] [--width 320 --height 288]
       [--frames-service 60] [--service-width 160 --service-height 144] [--keep DIR]

* stability: the built-in subject standing still, filmed by the 8-camera rig for
  --frames-static frames with the Azure Kinect noise model drawn anew for every frame; each
  frame reconstructed in-process (`pipeline.stages.reconstruct`, enhancement off). Reported:
  the frame-to-frame surface change of consecutive meshes (symmetric surface distance, mean
  and RMS, mm) next to the noise floor: each frame's error against the truth (C2M RMS), and
  the change expected of two independent reconstructions with that error (sqrt(2) x it).
  The same frame reconstructed twice measures the pipeline's own determinism.
* moving: the subject turning (60 degrees/s) and swaying (+-10 cm at 0.5 Hz) at 30 fps for
  --frames-moving frames; each frame's accuracy against that frame's truth.
* articulated: the same with the subject's upper half bowing (+-25 degrees at 0.5 Hz).
* throughput: the service as `volumesh serve` runs it (gateway, embedded file-system broker,
  SQLite) with one and then two worker processes (one task at a time each) on a
  --frames-service-frame capture at --service-width x --service-height (fast job options):
  frames per minute of a sequence job; its wall time per frame next to a single-frame job's
  wall time, and each frame's stage seconds next to the single job's. (A frame job's own span,
  first stage start to export, covers most of the sequence: every frame's first stage is
  queued at once, so one worker takes the frames breadth first.)
Prints one JSON object.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.api_common import (  # noqa: E402
    free_port,
    gateway_cmd,
    load_average,
    process,
    service_env,
    wait_http,
)

FAST_JOB = {"enhance": False, "target_edge_length_m": 0.04,
            "meshing": {"poisson_depth": 6, "sample_radius_m": 0.015},
            "remesh": {"iterations": 1}}
"""The service tests' fast options (tests/integration/services.py)."""
SAMPLES = 100_000


def _capture(folder: Path, frames: int, motion: str, width: int, height: int,
             seed: int = 0) -> tuple[Path, Any]:
    from pipeline.io.capture_io import write_capture
    from pipeline.synth.motion import MotionConfig, synthesize_sequence
    from pipeline.synth.rig import RigConfig
    from pipeline.synth.scene import SynthConfig, sample_mesh

    config = SynthConfig(seed=seed, frame_count=frames, rig=RigConfig(width=width, height=height))
    meta, views, truth = synthesize_sequence(sample_mesh(), config, MotionConfig(kind=motion))
    write_capture(folder / "capture", meta, views)
    return folder / "capture", truth


def _reconstruct(capture: Path, frame: int) -> tuple[Any, float]:
    from pipeline.io.capture_io import open_capture
    from pipeline.stage_config import config_from_options
    from pipeline.stages import reconstruct

    config = config_from_options({"enhance": False, "frame_index": frame})
    started = time.perf_counter()
    with open_capture(capture) as reader:
        mesh, _ = reconstruct(reader, config)
    return mesh, time.perf_counter() - started


def surface_change_mm(a: Any, b: Any) -> dict[str, float]:
    """Symmetric surface distance between two meshes: samples of each measured to the other."""
    from pipeline.reconstruct.quality import sample_surface, signed_distances_m

    a_points, _ = sample_surface(a, SAMPLES, seed=1)
    b_points, _ = sample_surface(b, SAMPLES, seed=2)
    both = np.abs(np.concatenate([signed_distances_m(a_points, b),
                                  signed_distances_m(b_points, a)]))
    return {"mean_mm": round(float(both.mean()) * 1e3, 3),
            "rms_mm": round(float(np.sqrt(np.mean(both**2))) * 1e3, 3),
            "p95_mm": round(float(np.percentile(both, 95)) * 1e3, 3)}


def _accuracy_mm(result: Any, truth: Any, cameras: list[Any]) -> dict[str, float]:
    from pipeline.reconstruct.quality import MetricsConfig, compare

    figures: dict[str, Any] = compare(result, truth, cameras,
                                      MetricsConfig(sample_count=SAMPLES))
    return {"c2m_rms_mm": round(figures["result_to_gt"]["rms_m"] * 1e3, 3),
            "c2m_p95_mm": round(figures["result_to_gt"]["p95_m"] * 1e3, 3),
            "coverage_visible": round(figures["coverage_visible"], 4)}


def _true_cameras(truth: Any) -> list[Any]:
    from pipeline.synth.scene import SynthConfig, true_cameras

    return true_cameras(truth.subject, SynthConfig())


def stability(folder: Path, frames: int, width: int, height: int) -> dict[str, Any]:
    capture, truth = _capture(folder, frames, "static", width, height)
    meshes, seconds, errors = [], [], []
    cameras = _true_cameras(truth)
    for frame in range(frames):
        mesh, took = _reconstruct(capture, frame)
        meshes.append(mesh)
        seconds.append(took)
        errors.append(_accuracy_mm(mesh, truth.mesh(frame), cameras))
    changes = [surface_change_mm(a, b) for a, b in zip(meshes, meshes[1:], strict=False)]
    again, _ = _reconstruct(capture, 0)
    rms_error = float(np.mean([e["c2m_rms_mm"] for e in errors]))
    change_rms = float(np.mean([c["rms_mm"] for c in changes]))
    return {
        "frames": frames, "width": width, "height": height, "cameras": 8,
        "frame_seconds_mean": round(float(np.mean(seconds)), 2),
        "consecutive_change_mm": {k: round(float(np.mean([c[k] for c in changes])), 3)
                                  for k in ("mean_mm", "rms_mm", "p95_mm")},
        "consecutive_change_rms_mm_max": round(max(c["rms_mm"] for c in changes), 3),
        "per_frame_c2m_rms_mm": [e["c2m_rms_mm"] for e in errors],
        "noise_floor_rms_mm": round(rms_error, 3),
        "independent_pair_change_rms_mm": round(math.sqrt(2) * rms_error, 3),
        "change_over_independent_pair": round(change_rms / (math.sqrt(2) * rms_error), 3),
        "same_frame_twice_mm": surface_change_mm(meshes[0], again),
    }


MOTION_TEXT = {"rigid": "rigid: 60 deg/s turn, +-10 cm sway at 0.5 Hz, 30 fps",
               "articulated": "articulated: the upper half bowing +-25 deg at 0.5 Hz about a "
                              "joint at half height, 30 fps"}


def moving(folder: Path, frames: int, width: int, height: int,
           kind: str = "rigid") -> dict[str, Any]:
    capture, truth = _capture(folder, frames, kind, width, height)
    cameras = _true_cameras(truth)
    per_frame = []
    for frame in range(frames):
        mesh, took = _reconstruct(capture, frame)
        per_frame.append({"frame": frame, "seconds": round(took, 2),
                          **_accuracy_mm(mesh, truth.mesh(frame), cameras)})
    rms = [f["c2m_rms_mm"] for f in per_frame]
    return {"frames": frames, "width": width, "height": height, "motion": MOTION_TEXT[kind],
            "c2m_rms_mm_mean": round(float(np.mean(rms)), 3), "c2m_rms_mm_max": round(max(rms), 3),
            "per_frame": per_frame}


# ----------------------------------------------------------------------------- the service

def _zip(folder: Path, frames: int, width: int, height: int) -> Path:
    from pipeline.io.capture_io import zip_capture

    target = folder / f"seq-{frames}"
    capture, _ = _capture(target, frames, "rigid", width, height)
    zip_capture(capture, target / "capture.zip")
    return target / "capture.zip"


def _seconds(job: dict[str, Any]) -> float:
    start = datetime.fromisoformat(job["started_at"])
    return (datetime.fromisoformat(job["finished_at"]) - start).total_seconds()


def _wait(client: Any, job_id: str, timeout_s: float) -> dict[str, Any]:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        job = client.get(f"/api/v1/jobs/{job_id}").json()
        if job["state"] in ("succeeded", "failed", "cancelled"):
            return dict(job)
        time.sleep(0.5)
    raise TimeoutError(f"job {job_id} unfinished after {timeout_s} s")


def _service_run(folder: Path, zips: dict[str, Path], workers: int) -> dict[str, Any]:
    """One service with ``workers`` worker processes: a single-frame job, then the sequence."""
    import httpx

    data = folder / f"service-{workers}"
    env = service_env(data_dir=str(data))
    made = subprocess.run([sys.executable, "-m", "app", "keys", "create", "--name", "bench"],
                          env=env, cwd=ROOT, capture_output=True, text=True, check=True)
    key = made.stdout.strip().splitlines()[-1]
    port = free_port()
    with contextlib.ExitStack() as running:
        running.enter_context(process(gateway_cmd(port, 1), env, data / "gateway.log"))
        for i in range(workers):
            running.enter_context(process(
                [sys.executable, "-m", "workers", "--queues", "cpu,gpu,validate",
                 "--concurrency", "1", "--hostname", f"w{i}@bench"], env,
                data / f"worker{i}.log"))
        wait_http(port)
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=120,
                          headers={"Authorization": f"Bearer {key}"}) as client:
            return _measure(client, zips)


def _measure(client: Any, zips: dict[str, Path]) -> dict[str, Any]:
    ids = {}
    for name, path in zips.items():
        upload = client.post("/api/v1/captures", content=path.read_bytes(),
                             headers={"Content-Type": "application/zip"})
        upload.raise_for_status()
        ids[name] = upload.json()["id"]
    single = client.post("/api/v1/jobs", json={"capture_id": ids["single"], **FAST_JOB})
    single_job = _wait(client, single.json()["id"], 300)
    started = time.monotonic()
    created = client.post("/api/v1/jobs", json={"capture_id": ids["sequence"], "frames": "all",
                                                **FAST_JOB})
    created.raise_for_status()
    sequence = _wait(client, created.json()["id"], 1800)
    wall_s = time.monotonic() - started
    frames = client.get("/api/v1/jobs", params={"parent_id": sequence["id"],
                                                "limit": 100}).json()["items"]
    done = [f for f in frames if f["state"] == "succeeded"]
    frame_stage_s = [sum(f["stage_timings"].values()) for f in done]
    return {"sequence_state": sequence["state"], "frames_done": sequence["frames_done"],
            "frames_failed": sequence["frames_failed"], "wall_s": round(wall_s, 1),
            "frames_per_minute": round(60 * len(done) / wall_s, 2),
            "wall_per_frame_s": round(wall_s / max(1, len(done)), 2),
            "single_capture_job_s": round(_seconds(single_job), 2),
            "frame_stage_s_mean": round(float(np.mean(frame_stage_s)), 2),
            "single_capture_stage_s": round(sum(single_job["stage_timings"].values()), 2),
            "frame_job_span_s_mean": round(float(np.mean([_seconds(f) for f in done])), 2),
            "load_average_after": round(load_average(), 2)}


def throughput(folder: Path, frames: int, width: int, height: int) -> dict[str, Any]:
    zips = {"sequence": _zip(folder, frames, width, height),
            "single": _zip(folder, 1, width, height)}
    runs = {f"{n}_worker{'s' if n > 1 else ''}": _service_run(folder, zips, n) for n in (1, 2)}
    one, two = runs["1_worker"], runs["2_workers"]
    return {"frames": frames, "width": width, "height": height, "cameras": 8,
            "options": FAST_JOB, "broker": "embedded (file system), SQLite", **runs,
            "speed_up_two_workers": round(two["frames_per_minute"] / one["frames_per_minute"], 2),
            "wall_per_frame_over_single_job_1_worker": round(
                one["wall_per_frame_s"] / one["single_capture_job_s"], 2),
            "frame_stage_over_single_stage_1_worker": round(
                one["frame_stage_s_mean"] / one["single_capture_stage_s"], 2)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--part", default="stability,moving,articulated,throughput")
    parser.add_argument("--frames-static", type=int, default=8)
    parser.add_argument("--frames-moving", type=int, default=6)
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=288)
    parser.add_argument("--frames-service", type=int, default=60)
    parser.add_argument("--service-width", type=int, default=160)
    parser.add_argument("--service-height", type=int, default=144)
    parser.add_argument("--keep", type=Path, default=None)
    args = parser.parse_args()
    parts = set(args.part.split(","))
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.keep or Path(tmp)
        result: dict[str, Any] = {"cpus": os.cpu_count(),
                                  "load_average_start": round(load_average(), 2)}
        if "stability" in parts:
            result["stability"] = stability(folder / "static", args.frames_static, args.width,
                                            args.height)
        if "moving" in parts:
            result["moving"] = moving(folder / "moving", args.frames_moving, args.width,
                                      args.height)
        if "articulated" in parts:
            result["moving_articulated"] = moving(folder / "articulated", args.frames_moving,
                                                  args.width, args.height, "articulated")
        if "throughput" in parts:
            result["throughput"] = throughput(folder / "service", args.frames_service,
                                              args.service_width, args.service_height)
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
