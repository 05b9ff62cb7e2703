"""Mesh-enhancement benchmark (the paper's protocol, on the bunny); prints JSON.

The protocol (`enhance_protocol.py`): the bunny scaled to 1 m height, remeshed to ~5 mm edges,
every vertex moved along its normal by uniform noise in ±1 cm (seeded). Each method's result
is scored with CloudCompare-style C2M, the reverse distance and the mean normal angle error,
with its time per mesh. The classical smoothers are swept over iteration counts and reported
at their best. Depth-level figures come from held-apart validation renders (meshes never
trained on). Targets are checked and reported as they come out.

    .venv/bin/python benchmarks/enhance.py [--weights DIR] [--quick]
        [--noise uniform|gaussian|laplace] > enhance.json

`--noise` draws Gaussian or Laplace noise of the uniform noise's standard deviation (5.77 mm)
instead, as sensors make it; uniform, the default, keeps the paper's protocol.

The timing alone, per stage, in this process (on a GPU: `--device cuda`):

    .venv/bin/python benchmarks/enhance.py --perf-child [--method regressor|ldm|classical]
        [--device cuda] [--remesh-iterations 0]
        [--remesh auto|ahead|after] [--warm-up small|full] [--networks loaded|kept]
        [--min-piece-faces N] [--profile FILE]
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import resource
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from enhance_protocol import (  # noqa: E402
    MESHES,
    NO_BOUNDED_NOISE,
    NO_NORMAL_FILTER,
    NOISE_KINDS,
    SWEEPS,
    adaptive_twicing,
    best_normal_filtering,
    best_of_sweep,
    bunny_protocol,
    classical,
    presmoothing,
    run_method,
    score,
    targets,
    twicing_bounded_noise,
    weights_folder,
)

from pipeline.enhance import EnhanceConfig, enhance_mesh  # noqa: E402
from pipeline.enhance.config import METHODS  # noqa: E402
from pipeline.enhance.enhancement import CHECKED_STAGE_PROGRESS, STAGE_PROGRESS  # noqa: E402
from pipeline.enhance.networks import load_networks  # noqa: E402
from pipeline.enhance.training.data import DataConfig  # noqa: E402

__all__ = ["bunny_protocol", "score"]  # what other benchmarks import from here

VERTEX_NOISE_ONLY = DataConfig(
    poses_per_mesh=2, edge_fraction=(0.005, 0.005), noise_fraction=(0.01, 0.01),
    light_noise_probability=0.0, kinect_probability=0.0, hole_probability=0.0,
    downup_probability=0.0, color_probability=0.0,
)
"""The benchmark's degradation alone (its noise and edge length relative to the mesh, no
sensor noise, holes, resampling or colour), for depth-level figures on held-apart meshes."""


NOISE_DESCRIPTIONS = {
    "uniform": "uniform +-1 cm along vertex normals",
    "gaussian": "Gaussian along vertex normals, std 5.77 mm (that of uniform +-1 cm)",
    "laplace": "Laplace along vertex normals, std 5.77 mm (that of uniform +-1 cm)",
}
"""The report's words for each `--noise`."""


def depth_level(weights: dict | None, views: int, seed: int, meshes: Path) -> dict:
    """RMSE and 3-pixel edge-band RMSE on validation renders of held-apart meshes, and how
    the networks' corrections are calibrated on the benchmark's degradation alone."""
    import cv2

    from pipeline.enhance.training.data import make_pairs, procedural_meshes
    from pipeline.enhance.training.validate import depth_scores, noisy_input
    from pipeline.io.mesh_io import read_mesh

    val = [(n, read_mesh(meshes / f"{n}.obj")) for n in ("spot", "fandisk")]
    val += procedural_meshes(np.random.default_rng(seed), 7)[-1:]
    pairs = make_pairs(val, DataConfig(poses_per_mesh=2), seed + 1000)
    idx = np.unique(np.linspace(0, len(pairs.source) - 1, views).round().astype(np.int64))
    valid = pairs.degraded_valid[idx]
    noisy = noisy_input(pairs, idx)
    out = {"views": len(idx), "sources": sorted(set(pairs.source)), "units": "1e-3 of depth range"}
    # The image filters get the noisy render, as they would without the networks' pre-smoothing.
    out["noisy"] = depth_scores(noisy, pairs, idx)
    out["presmoothed"] = depth_scores(pairs.degraded_n[idx], pairs, idx)
    bil = np.stack([cv2.bilateralFilter(d, 5, 0.01, 2.0) for d in noisy])
    out["bilateral_filter"] = depth_scores(np.where(valid, bil, noisy), pairs, idx)
    jbu = []
    for d in noisy:
        h, w = d.shape
        low = cv2.resize(d, (w // 4, h // 4), interpolation=cv2.INTER_AREA)
        up = cv2.resize(low, (w, h), interpolation=cv2.INTER_LINEAR)
        jbu.append(cv2.ximgproc.jointBilateralFilter(d, up, 7, 0.01, 3.0))
    out["joint_bilateral_upsampling"] = depth_scores(
        np.where(valid, np.stack(jbu), noisy), pairs, idx
    )
    for name, pred in network_predictions(weights, pairs, idx, (1, 4, 10)).items():
        out[name] = {"error": pred} if isinstance(pred, str) else depth_scores(pred, pairs, idx)
    out["vertex_noise_only"] = calibration(
        make_pairs(val[:2], VERTEX_NOISE_ONLY, seed + 2000), weights, views
    )
    return out


def calibration(pairs, weights: dict | None, views: int) -> dict:
    """Depth scores of the base and the networks, with how their corrections match the true
    ones (`correction_calibration`: least-squares gain, correlation, bias)."""
    from pipeline.enhance.metrics import correction_calibration
    from pipeline.enhance.training.data import same_surface_mask
    from pipeline.enhance.training.validate import depth_scores

    idx = np.unique(np.linspace(0, len(pairs.source) - 1, views).round().astype(np.int64))
    base, clean, mask = pairs.degraded_n[idx], pairs.clean_n[idx], same_surface_mask(pairs, idx)
    out: dict = {"views": len(idx), "presmoothed": depth_scores(base, pairs, idx)}
    for name, pred in network_predictions(weights, pairs, idx, (4,)).items():
        out[name] = {"error": pred} if isinstance(pred, str) else {
            **depth_scores(pred, pairs, idx), **correction_calibration(pred, base, clean, mask)
        }
    return out


def network_predictions(weights: dict | None, pairs, idx, ldm_steps: tuple[int, ...]) -> dict:
    """(n, H, W) predictions of the regressor and of the LDM at each step count on the pairs
    `idx`; a model whose weights do not load gives its error message instead."""
    import torch

    from pipeline.enhance.models.common import side_inputs
    from pipeline.enhance.pipelines.depth_ldm import enhance_depth_ldm
    from pipeline.enhance.training.validate import noisy_input
    from pipeline.enhance.weights import shipped_bytes
    from pipeline.enhance.weights.loading import load_ldm, load_regressor

    def get(name: str) -> bytes:
        return weights[name] if weights and name in weights else shipped_bytes(name)

    d_t = torch.from_numpy(pairs.degraded_n[idx][:, None])
    v_t = torch.from_numpy(pairs.degraded_valid[idx][:, None])
    side_t = side_inputs(torch.from_numpy(pairs.edges[idx][:, None]),
                         torch.from_numpy(noisy_input(pairs, idx)[:, None]), d_t, v_t)
    batches = [slice(i, i + 6) for i in range(0, len(idx), 6)]
    out: dict = {}
    with torch.no_grad():
        try:
            reg = load_regressor(get("regressor"))
            out["regressor"] = torch.cat(
                [reg(d_t[b], v_t[b], side_t[b]) for b in batches]
            )[:, 0].numpy()
        except ValueError as exc:
            out["regressor"] = str(exc)
        try:
            models = load_ldm(get("vae"), get("ldm"))
            for steps in ldm_steps:
                out[f"ldm_{steps}_steps"] = torch.cat(
                    [enhance_depth_ldm(models, d_t[b], v_t[b], steps, 0.5, 0, side_t[b])
                     for b in batches]
                )[:, 0].numpy()
        except ValueError as exc:
            out["ldm"] = str(exc)
    return out


def _recording_remesh_stats(stats: dict) -> None:
    """The light remesh's stats (`remesh.remesh`'s, or `finish_remesh_ahead`'s on the remesh
    started ahead) of the next `enhance_mesh`, with the seconds of that call, put in
    `stats`: the kernel's wait, the clean-up's counts. The calls themselves are unchanged."""
    import pipeline.enhance.clean.light_remesh as light
    import pipeline.enhance.enhancement as enhancement

    def recorded(call):
        def wrapper(*args, **kwargs):
            start = time.perf_counter()
            out = call(*args, **kwargs)
            stats.update(out[1], seconds=time.perf_counter() - start)
            return out
        return wrapper

    light.remesh = recorded(light.remesh)
    enhancement.finish_remesh_ahead = recorded(enhancement.finish_remesh_ahead)


def perf_child(args) -> None:
    """Runs one enhancement (`--method`, by default the product's) in this fresh process and
    prints seconds, the seconds of each stage (`STAGE_PROGRESS`), the light remesh's wait for
    its kernel and peak RSS. A warm-up call runs first: at 32² (`--warm-up small`: imports
    and first-call costs, not the shapes of the timed call), or the timed call itself
    (`--warm-up full`: a worker's second mesh, the accelerator's kernels for these shapes
    chosen already). With `--networks kept`
    the networks are loaded before the warm-up and both calls are given them
    (`networks.load_networks`), as a worker keeps them between jobs; `loaded`: each call
    loads its own. `--min-piece-faces` sets `remesh.MIN_PIECE_FACES` for both calls, to
    time another piece count on the device machine's cores; `--self-check` turns the
    self-check on (its stage is "check")."""
    import pipeline.reconstruct.remesh.isotropic

    if args.min_piece_faces is not None:
        pipeline.reconstruct.remesh.isotropic.MIN_PIECE_FACES = args.min_piece_faces
    truth, noisy = bunny_protocol(Path(args.meshes), args.seed, 1e-3 * args.edge_mm,
                                  name=args.mesh, noise=args.noise)
    weights = weights_folder(args.weights)
    cfg = EnhanceConfig(
        method=args.method, views=args.views, resolution=args.resolution, steps=args.steps,
        remesh_iterations=args.remesh_iterations, device=args.device, weights=weights,
        remesh_ahead={"auto": None, "ahead": True, "after": False}[args.remesh],
        self_check=args.self_check,
    )
    networks = load_networks(cfg) if args.networks == "kept" else None
    enhance_mesh(noisy, cfg if args.warm_up == "full" else replace(cfg, resolution=32),
                 networks=networks)
    remesh_stats: dict = {}
    _recording_remesh_stats(remesh_stats)
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    shares = CHECKED_STAGE_PROGRESS if args.self_check else STAGE_PROGRESS
    stage_of = {share: stage for stage, share in shares.items()}
    checks: list = []
    ends = [("start", time.perf_counter())]
    profiler = cProfile.Profile() if args.profile else None
    if profiler:
        profiler.enable()
    enhance_mesh(noisy, cfg, lambda share: ends.append((stage_of[share], time.perf_counter())),
                 networks, checks.append)
    if profiler:
        profiler.disable()
        with open(args.profile, "w") as f:
            stats = pstats.Stats(profiler, stream=f)
            stats.sort_stats("cumulative").print_stats(70)
            stats.sort_stats("tottime").print_stats(40)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    stages = {name: t - before for (_, before), (name, t) in zip(ends, ends[1:], strict=False)}
    print(json.dumps({
        "mesh": args.mesh, "method": args.method, "seconds": ends[-1][1] - ends[0][1],
        "stage_seconds": stages, "device": args.device,
        "remesh_iterations": args.remesh_iterations, "warm_up": args.warm_up,
        "networks": args.networks,
        "self_checked": args.self_check, "profiled": profiler is not None,
        "self_check": checks[0].as_stats() if checks else None,
        "kernel_pieces": (pipeline.reconstruct.remesh.isotropic.kernel_piece_count(
            noisy.face_count, None)
                          if args.remesh_iterations else 0),
        "remesh_call_seconds": remesh_stats.get("seconds"),
        "kernel_wait_seconds": remesh_stats.get("kernel_wait_s"),
        "angle_cleanup": remesh_stats.get("angle_cleanup"),
        "peak_rss_gb": peak / 2**20, "rss_before_gb": base / 2**20,
    }))


def fresh_process_timing(args, remesh_iterations: int) -> dict:
    """`perf_child`'s figures from a fresh interpreter."""
    child = [sys.executable, __file__, "--perf-child", "--meshes", args.meshes, "--mesh", args.mesh]
    child += ["--views", str(args.views), "--resolution", str(args.resolution)]
    child += ["--remesh-iterations", str(remesh_iterations), "--edge-mm", str(args.edge_mm)]
    child += ["--noise", args.noise, "--method", args.method]
    child += ["--weights", args.weights] if args.weights else []
    proc = subprocess.run(child, capture_output=True, text=True)
    if proc.returncode != 0:
        return {"error": proc.stderr.strip().splitlines()[-1:]}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--meshes", default=str(MESHES))
    ap.add_argument("--weights", default=None, help="folder of .safetensors (default: shipped)")
    ap.add_argument("--mesh", default="stanford-bunny",
                    help="protocol mesh: a name in --meshes or a mesh file (default: the bunny)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--noise", choices=NOISE_KINDS, default="uniform",
                    help="the noise along normals: uniform in +-1 cm (the paper's protocol), or "
                    "Gaussian or Laplace of the same standard deviation")
    ap.add_argument("--views", type=int, default=6)
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--depth-views", type=int, default=24)
    ap.add_argument("--quick", action="store_true", help="coarser sweeps, no depth-level part")
    ap.add_argument("--perf-child", action="store_true",
                    help="only time one LDM enhancement (with its stages) in this process")
    ap.add_argument("--device", default="auto", help="torch device of the timing: auto, cpu, cuda")
    ap.add_argument("--profile", default=None,
                    help="with --perf-child: write cProfile's figures of the timed call here")
    ap.add_argument("--remesh-iterations", type=int, default=1,
                    help="light remesh rounds of the timing (0: none)")
    ap.add_argument("--remesh", choices=["auto", "ahead", "after"], default="auto",
                    help="with --perf-child: the light remesh started ahead of the update "
                    "(`remesh_ahead`), after it, or as the device's default")
    ap.add_argument("--warm-up", choices=["small", "full"], default="small",
                    help="with --perf-child: the warm-up call at 32² or as the timed call")
    ap.add_argument("--networks", choices=["loaded", "kept"], default="loaded",
                    help="with --perf-child: each call loads its networks, or they are loaded "
                    "once and kept, as a worker keeps them between jobs")
    ap.add_argument("--min-piece-faces", type=int, default=None,
                    help="with --perf-child: the light remesh's kernel pieces have at least this "
                    "many faces (`remesh.MIN_PIECE_FACES`; fewer: more pieces, up to one a core)")
    ap.add_argument("--self-check", action="store_true",
                    help="with --perf-child: the self-check on (`EnhanceConfig.self_check`)")
    ap.add_argument("--edge-mm", type=float, default=5.0,
                    help="the protocol's edge length, mm (finer: a larger mesh, for timings)")
    ap.add_argument("--steps", type=int, default=4, help=argparse.SUPPRESS)
    ap.add_argument("--method", choices=METHODS, default=EnhanceConfig().method,
                    help="the method timed in a fresh process (default: the product's)")
    args = ap.parse_args()
    if args.perf_child:
        perf_child(args)
        return
    import torch

    torch.set_num_threads(max(1, torch.get_num_threads()))
    weights = weights_folder(args.weights)
    meshes = Path(args.meshes)
    truth, noisy = bunny_protocol(meshes, args.seed, 1e-3 * args.edge_mm, name=args.mesh,
                                  noise=args.noise)
    report: dict = {
        "protocol": {
            "mesh": f"{args.mesh}, 1 m high, long boundary edges split, remeshed to "
                    f"{args.edge_mm:g} mm edges (gpytoolbox remesh_botsch)",
            "vertices": truth.vertex_count,
            "noise": NOISE_DESCRIPTIONS[args.noise],
            "seed": args.seed,
            "views": args.views,
            "resolution": args.resolution,
            "torch_threads": torch.get_num_threads(),
            "cpu_count": os.cpu_count(),
            "load_average_at_start": os.getloadavg(),
        },
        "methods": {},
    }
    methods = report["methods"]
    methods["noisy"] = score(noisy, truth, 0.0)
    for name, counts in SWEEPS.items():
        methods[name] = best_of_sweep(noisy, truth, name, counts[::3] if args.quick else counts)
    base = EnhanceConfig(views=args.views, resolution=args.resolution, weights=weights)
    methods["adaptive_twicing"] = adaptive_twicing(noisy, truth)
    # The pre-smoothing alone, with and without its midrange estimator; the same on plain
    # twicing at its best count; the classical method (the pre-smoothing and the ending).
    methods["selector"] = presmoothing(noisy, truth, base, base.bounded_noise)
    methods["selector_without_bounded_noise"] = presmoothing(noisy, truth, base,
                                                             NO_BOUNDED_NOISE)
    methods["twicing_bounded_noise"] = twicing_bounded_noise(
        noisy, truth, methods["twicing"]["iterations"])
    methods["classical"] = classical(noisy, truth, base)
    methods["bilateral_normal_filtering"] = best_normal_filtering(noisy, truth)
    for label, cfg in (
        ("regressor", replace(base, method="regressor")),
        ("ldm_1_step", replace(base, method="ldm", steps=1)),
        ("ldm_4_steps", replace(base, method="ldm", steps=4)),
        ("ldm_10_steps", replace(base, method="ldm", steps=10)),
        ("ldm_1_step_14_views", replace(base, method="ldm", steps=1, views=14)),
        # Without the light remesh, which is most of the time on a CPU and all of it on a GPU.
        ("ldm_4_steps_no_remesh", replace(base, method="ldm", steps=4, remesh_iterations=0)),
        ("regressor_no_remesh", replace(base, method="regressor", remesh_iterations=0)),
        # Without the bilateral normal filter that ends the update: what it adds.
        ("ldm_4_steps_no_normal_filter", replace(base, method="ldm", steps=4,
                                                 normal_filter=NO_NORMAL_FILTER)),
        ("regressor_no_normal_filter", replace(base, method="regressor",
                                               normal_filter=NO_NORMAL_FILTER)),
        # Without the midrange estimator, as on noise with tails.
        ("ldm_4_steps_without_bounded_noise", replace(base, method="ldm", steps=4,
                                                      bounded_noise=NO_BOUNDED_NOISE)),
        ("regressor_without_bounded_noise", replace(base, method="regressor",
                                                    bounded_noise=NO_BOUNDED_NOISE)),
    ):
        try:
            run_method(noisy, truth, replace(cfg, resolution=32))  # warm-up (imports, loading)
            methods[label] = run_method(noisy, truth, cfg)
        except ValueError as exc:
            methods[label] = {"error": str(exc)}
    report["fresh_process"] = fresh_process_timing(args, remesh_iterations=1)
    report["fresh_process_no_remesh"] = fresh_process_timing(args, 0)
    if not args.quick:
        report["depth_level"] = depth_level(weights, args.depth_views, args.seed, meshes)
    report["load_average_at_end"] = os.getloadavg()
    report["targets"] = targets(methods, report["fresh_process"])
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
