"""The enhancement judged on what volumesh serves: its own reconstructions; prints JSON.

    .venv/bin/python benchmarks/enhance_reconstructions.py [--meshes DIR] [--mesh NAME ...]
        [--condition NAME ...] [--seed N] [--samples N]

For each mesh (default: the validation meshes, spot and fandisk, and the bunny, the test
model; none of them trained on) and each rig condition (`CONDITIONS`: full and binned depth
modes, 4 to 8 cameras, subjects 1 to 2 m tall, colour on and off, every written pose off by
up to 1 mm and 0.1 degrees, the Azure Kinect noise model), a synthetic capture is
reconstructed as `volumesh reconstruct --no-enhance` does it (`plain`), and that mesh is then:

* `enhanced`: the enhance stage as `volumesh reconstruct --enhance` runs it (noise gate, the
  default network);
* `ldm` and `regressor`: `enhance_mesh` with the gate passed, each depth network;
* `classical`: the classical method (pre-smoothing, normal filter, light remesh);
* `oracle_smoothing`: the best of Laplacian, Taubin, twicing and bilateral normal filtering
  over their counts, chosen by the C2M RMS against the truth (which a user never has), no
  smoothing among the choices.

Every result is measured against the truth with `pipeline.reconstruct.quality.compare`: C2M
RMS (result to truth), the mean normal error over the result's area, the coverage of the
observed truth within 5 mm, and the RMS distances apart on the truth no camera observes
(`unobserved`) and on the rest (`observed`). `summary` gives each method's ratios to plain over
the validation meshes against issue 49's targets.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from enhance_protocol import MESHES, protocol_mesh_file  # noqa: E402

from pipeline.enhance import EnhanceConfig, enhance_mesh  # noqa: E402
from pipeline.enhance.enhancement import past_the_gate  # noqa: E402
from pipeline.geometry import smoothing  # noqa: E402
from pipeline.geometry.mesh import TriangleMesh  # noqa: E402
from pipeline.io.capture_io import open_capture, write_capture  # noqa: E402
from pipeline.io.mesh_io import read_mesh  # noqa: E402
from pipeline.reconstruct.quality import MetricsConfig, compare, signed_distances_m  # noqa: E402
from pipeline.stage_artifacts import stage_stats  # noqa: E402
from pipeline.stage_config import config_from_options  # noqa: E402
from pipeline.stage_enhance import stage_enhance  # noqa: E402
from pipeline.stages import reconstruct  # noqa: E402
from pipeline.synth.rig import RigConfig  # noqa: E402
from pipeline.synth.scene import SynthConfig, synthesize, true_cameras  # noqa: E402

VALIDATION = ("spot", "fandisk")
TEST = ("stanford-bunny",)


@dataclass(frozen=True)
class Condition:
    """One rig condition of the validation captures."""

    cameras: int
    width: int
    height: int
    subject_height_m: float
    color: bool


CONDITIONS = {
    "full-8": Condition(8, 640, 576, 1.8, True),
    "binned-8": Condition(8, 320, 288, 1.8, False),
    "full-4": Condition(4, 640, 576, 1.0, True),
    "binned-6": Condition(6, 320, 288, 2.0, True),
}
"""Full depth mode is the Azure Kinect's NFOV unbinned (640x576), binned its 2x2 (320x288)."""
POSE_ERROR_DEG, POSE_ERROR_M = 0.1, 0.001
SWEEPS: dict[str, tuple[int, ...]] = {
    "laplacian": (1, 2, 4, 8), "taubin": (2, 5, 10, 20), "twicing": (5, 10, 20, 40)}
NORMAL_FILTERING = tuple((sigma, passes) for sigma in (0.35, 0.7, 1.4) for passes in (1, 3, 10))


def capture_and_truth(mesh: TriangleMesh, condition: Condition, seed: int, folder: Path
                      ) -> tuple[Path, TriangleMesh, list]:
    config = SynthConfig(model_height_m=condition.subject_height_m, seed=seed,
                         camera_count=condition.cameras, with_color=condition.color,
                         rig=RigConfig(width=condition.width, height=condition.height),
                         pose_error_rot_deg=POSE_ERROR_DEG, pose_error_trans_m=POSE_ERROR_M)
    meta, views, truth = synthesize(mesh, config)
    write_capture(folder, meta, views)
    return folder, truth, true_cameras(truth, config)


def figures(result: TriangleMesh, truth: TriangleMesh, cameras: list, samples: int,
            seconds: float) -> dict[str, Any]:
    measured: Any = compare(result, truth, cameras, MetricsConfig(sample_count=samples))

    def mm(value: float | None) -> float | None:
        return None if value is None else round(value * 1e3, 3)

    return {"c2m_rms_mm": mm(measured["result_to_gt"]["rms_m"]),
            "normal_mean_deg": round(measured["normal_error_deg"]["mean"], 2),
            "coverage_observed": round(measured["coverage_visible"], 4),
            "observed_c2m_rms_mm": mm(measured["observed"]["result_to_gt_rms_m"]),
            "unobserved_c2m_rms_mm": mm(measured["unobserved"]["result_to_gt_rms_m"]),
            "unobserved_truth_to_result_rms_mm": mm(measured["unobserved"]["gt_to_result_rms_m"]),
            "unobserved_share": round(measured["unobserved"]["truth_share"], 4),
            "triangles": result.face_count, "seconds": round(seconds, 2)}


def oracle_smoothing(plain: TriangleMesh, truth: TriangleMesh) -> tuple[TriangleMesh, dict]:
    """The smoothing with the lowest RMS distance of its vertices to the truth, no smoothing
    included."""
    def candidates() -> Iterator[tuple[dict, TriangleMesh]]:
        yield {"smoother": "none"}, plain
        for name, counts in SWEEPS.items():
            smoother = getattr(smoothing, f"{name}_smooth")
            for k in counts:
                yield {"smoother": name, "iterations": k}, smoother(plain, k)
        for sigma, passes in NORMAL_FILTERING:
            config = smoothing.NormalFilteringConfig(passes, sigma, 30)
            yield ({"smoother": "bilateral_normal_filtering", "range_sigma": sigma,
                    "normal_passes": passes},
                   smoothing.bilateral_normal_filtering(plain, config))

    def rms(mesh: TriangleMesh) -> float:
        return float(np.sqrt(np.mean(signed_distances_m(mesh.vertices_m, truth) ** 2)))

    _, choice, best = min(((rms(mesh), choice, mesh) for choice, mesh in candidates()),
                          key=lambda c: c[0])
    return best, choice


def capture_row(mesh_file: Path, condition_name: str, seed: int, samples: int) -> dict:
    condition = CONDITIONS[condition_name]
    with tempfile.TemporaryDirectory() as tmp:
        folder, truth, cameras = capture_and_truth(read_mesh(mesh_file), condition, seed,
                                                   Path(tmp) / "capture")
        config = config_from_options({"enhance": False})
        started = time.perf_counter()
        with open_capture(folder) as reader:
            plain, _ = reconstruct(reader, config)
            plain_s = time.perf_counter() - started
            row: dict[str, Any] = {"mesh": mesh_file.stem, "condition": condition_name,
                                   "plain": figures(plain, truth, cameras, samples, plain_s)}
            started = time.perf_counter()
            stage = stage_enhance(reader, {"vertices_m": plain.vertices_m,
                                           "faces": plain.faces},
                                  replace(config, enhance=True), None)
            stats = stage_stats(stage)["enhance"]
            enhanced = TriangleMesh(stage["vertices_m"], stage["faces"])
            row["enhanced"] = figures(enhanced, truth, cameras, samples,
                                      time.perf_counter() - started) | {
                "skipped_as_clean": stats["skipped_as_clean"],
                "noise_ratio": round(stats["noise_ratio"], 4)}
        for method in ("ldm", "regressor", "classical"):
            started = time.perf_counter()
            out = enhance_mesh(plain, past_the_gate(EnhanceConfig(method=method)))
            row[method] = figures(out, truth, cameras, samples, time.perf_counter() - started)
        started = time.perf_counter()
        smoothed, choice = oracle_smoothing(plain, truth)
        row["oracle_smoothing"] = figures(smoothed, truth, cameras, samples,
                                          time.perf_counter() - started) | choice
    return row


METHODS = ("enhanced", "ldm", "regressor", "classical", "oracle_smoothing")
RATIOS = {"c2m_rms_mm": 0.85, "normal_mean_deg": 0.85, "unobserved_c2m_rms_mm": 0.7,
          "unobserved_truth_to_result_rms_mm": 0.7}
"""Issue 49's targets: each figure's ratio to plain at most this on the validation meshes. On
the unobserved part both ways count: a hole has no result to be far from the truth, and only
the truth's distance to the result sees it."""


def summary(rows: list[dict]) -> dict:
    """Per method, over the validation meshes' captures: the mean ratio of each figure to
    plain's, the captures where C2M RMS or the normals got worse, and whether the targets
    hold (coverage no lower on every capture, never worse than plain)."""
    validation = [r for r in rows if r["mesh"] in VALIDATION]
    out: dict[str, Any] = {"captures": len(validation)}
    for method in METHODS:
        ratios = {figure: round(float(np.mean([r[method][figure] / r["plain"][figure]
                                               for r in validation
                                               if r["plain"][figure]
                                               and r[method][figure] is not None])), 3)
                  for figure in RATIOS if validation}
        worse = [f"{r['mesh']}/{r['condition']}" for r in validation
                 if r[method]["c2m_rms_mm"] > r["plain"]["c2m_rms_mm"]
                 or r[method]["normal_mean_deg"] > r["plain"]["normal_mean_deg"]]
        lower = [f"{r['mesh']}/{r['condition']}" for r in validation
                 if r[method]["coverage_observed"] < r["plain"]["coverage_observed"]]
        out[method] = {"ratio_to_plain": ratios, "worse_than_plain": worse,
                       "coverage_lower": lower,
                       "targets_met": bool(validation) and not worse and not lower
                       and all(ratios[f] <= limit for f, limit in RATIOS.items())}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--meshes", type=Path, default=MESHES)
    parser.add_argument("--mesh", action="append", help="mesh name or file (repeatable)")
    parser.add_argument("--condition", action="append", choices=sorted(CONDITIONS))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--samples", type=int, default=100_000,
                        help="surface samples per mesh for the figures")
    args = parser.parse_args()
    names = args.mesh or [*VALIDATION, *TEST]
    rows = []
    for name in names:
        for condition in args.condition or list(CONDITIONS):
            row = capture_row(protocol_mesh_file(args.meshes, name), condition, args.seed,
                              args.samples)
            print(json.dumps(row), file=sys.stderr, flush=True)
            rows.append(row)
    print(json.dumps({"seed": args.seed, "load_average": os.getloadavg(),
                      "pose_error": {"deg": POSE_ERROR_DEG, "m": POSE_ERROR_M},
                      "conditions": {k: vars(v) for k, v in CONDITIONS.items()},
                      "rows": rows, "summary": summary(rows)}, indent=1))


if __name__ == "__main__":
    main()
