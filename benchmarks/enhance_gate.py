"""Where the networks stop helping: `EnhanceConfig.min_noise_ratio`, measured; prints JSON.

    .venv/bin/python benchmarks/enhance_gate.py [--mesh spot --mesh fandisk] > gate.json

Each mesh under the enhance benchmark's protocol (1 m high, 5 mm edges) with the noise
amplitude along the normals swept: C2M RMS of the noisy input and of the LDM's result with
the gate off, the estimated `noise_to_edge_ratio`, and the ratio at which the two errors cross
(linear between the sweep's points). Choose the gate on validation meshes (spot, fandisk),
never on the bunny. Also the synthetic bunny capture's reconstruction, with and without
enhancement (`volumesh synth` then the pipeline, in-process).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from enhance import bunny_protocol  # noqa: E402

from pipeline.enhance import EnhanceConfig, enhance_mesh  # noqa: E402
from pipeline.enhance.metrics import c2m_summary  # noqa: E402
from pipeline.enhance.noise_level import noise_to_edge_ratio  # noqa: E402
from pipeline.enhance.training.data import noisy_along_normals  # noqa: E402

AMPLITUDES_MM = (0.5, 1.0, 1.5, 2.0, 3.0, 5.0, 10.0)
UNGATED = EnhanceConfig(min_noise_ratio=0.0)


def crossover(rows: list[dict]) -> float | None:
    """The noise ratio where the enhanced error falls below the input's, interpolated."""
    for a, b in zip(rows, rows[1:], strict=False):
        da, db = a["ldm_rms_mm"] - a["input_rms_mm"], b["ldm_rms_mm"] - b["input_rms_mm"]
        if da > 0 >= db:
            t = da / (da - db)
            return a["noise_ratio"] + t * (b["noise_ratio"] - a["noise_ratio"])
    return None


def sweep(name: str, meshes: Path) -> dict:
    truth, _ = bunny_protocol(meshes, 0, name=name)
    rows = [{"amplitude_mm": 0.0, "noise_ratio": noise_to_edge_ratio(truth), "input_rms_mm": 0.0,
             "ldm_rms_mm": c2m_summary(enhance_mesh(truth, UNGATED), truth)["c2m_rms_mm"]}]
    for amplitude_mm in AMPLITUDES_MM:
        noisy = noisy_along_normals(truth, amplitude_mm / 1000, np.random.default_rng(1))
        rows.append({
            "amplitude_mm": amplitude_mm,
            "noise_ratio": noise_to_edge_ratio(noisy),
            "input_rms_mm": c2m_summary(noisy, truth)["c2m_rms_mm"],
            "ldm_rms_mm": c2m_summary(enhance_mesh(noisy, UNGATED), truth)["c2m_rms_mm"],
        })
    return {"rows": rows, "crossover_noise_ratio": crossover(rows)}


def reconstruction(meshes: Path) -> dict:
    from pipeline.io.capture_io import open_capture
    from pipeline.io.mesh_io import read_mesh
    from pipeline.reconstruct.quality import MetricsConfig, compare
    from pipeline.stage_config import config_from_options
    from pipeline.stages import posed_cameras, reconstruct

    with tempfile.TemporaryDirectory() as tmp:
        # As the README's reconstruction figures: the CLI's synthetic capture of the bunny.
        subprocess.run([sys.executable, "-c", "from app.cli import main; main()", "synth",
                        "--mesh", str(meshes / "stanford-bunny.obj"), "--out", f"{tmp}/cap"],
                       cwd=ROOT, check=True, capture_output=True)
        gt = read_mesh(Path(tmp) / "cap" / "ground_truth.ply")
        config = config_from_options({})
        with open_capture(Path(tmp) / "cap") as reader:
            mesh, _ = reconstruct(reader, config)
            cameras = posed_cameras(reader.meta, config)

    def rms_mm(m) -> float:
        return 1e3 * compare(m, gt, cameras, MetricsConfig())["result_to_gt"]["rms_m"]

    return {
        "noise_ratio": noise_to_edge_ratio(mesh),
        "plain_rms_mm": rms_mm(mesh),
        "enhanced_ungated_rms_mm": rms_mm(enhance_mesh(mesh, UNGATED)),
        "enhanced_default_rms_mm": rms_mm(enhance_mesh(mesh, EnhanceConfig())),
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--meshes", default=str(ROOT.parent / "shared" / "data" / "meshes"))
    ap.add_argument("--mesh", action="append", help="protocol meshes (default: spot, fandisk)")
    args = ap.parse_args()
    meshes = Path(args.meshes)
    report: dict = {name: sweep(name, meshes) for name in args.mesh or ["spot", "fandisk"]}
    report["bunny_capture_reconstruction"] = reconstruction(meshes)
    report["min_noise_ratio"] = EnhanceConfig().min_noise_ratio
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
