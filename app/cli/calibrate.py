"""`volumesh calibrate`: camera extrinsics from a ChArUco calibration capture."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from app.cli import app


@app.command()
def calibrate(
    capture: Annotated[Path, typer.Argument(help="Calibration capture: directory or .zip "
                                            "(capture format v1 with a target).")],
    out: Annotated[Path, typer.Option("--out", help="Rig file to write (rig.json).")],
    icp: Annotated[bool, typer.Option("--icp", help="Refine the depth cameras by ICP between "
                                      "their depth clouds after the ChArUco fit.")] = False,
    reference: Annotated[str | None, typer.Option(
        "--reference", help="Camera whose depth frame defines the world (default: the "
        "first).")] = None,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the random frame subsets.")] = 0,
) -> None:
    """Writes OUT with world_from_depth per camera and the calibration's quality report."""
    from tqdm import tqdm

    from app.cli.paths import output_file
    from pipeline.calibration import CalibrationConfig
    from pipeline.calibration import calibrate as run_calibration
    from pipeline.io.capture_io import open_capture
    from pipeline.io.rig_io import write_rig

    output_file(out)
    config = CalibrationConfig(icp=icp, reference_camera=reference, seed=seed)
    with open_capture(capture) as reader, tqdm(total=100, desc="calibrate", unit="%") as bar:
        def advance(fraction: float) -> None:
            bar.update(max(0, round(fraction * 100) - bar.n))

        world_from_depth, report = run_calibration(reader, config, progress=advance)
    write_rig(out, world_from_depth, report)
    rms = report["reprojection_rms_px"]
    tri = report["triangulation_error_mm"]
    typer.echo(f"wrote {out}: {len(world_from_depth)} cameras, reprojection RMS "
               f"{min(rms.values()):.3f}-{max(rms.values()):.3f} px, triangulation error "
               f"median {tri.get('median', float('nan')):.2f} mm")
    for warning in report["warnings"]:
        typer.echo(f"warning: {warning}", err=True)
