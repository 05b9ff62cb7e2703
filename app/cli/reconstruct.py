"""`volumesh reconstruct`: a capture in, a clean mesh (.glb with Draco, or .ply) out."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any

import typer

from app.cli import app


def _read_rig(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise ValueError(f"--rig: {path} not found")
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"--rig: {path} is not readable JSON ({exc})") from None
    if not isinstance(doc, dict) or "world_from_depth" not in doc:
        raise ValueError(f"--rig: {path} has no \"world_from_depth\" object")
    return {"world_from_depth": doc["world_from_depth"]}


def _options(rig: Path | None, frame: int | None, edge_length_mm: float | None
             ) -> dict[str, Any]:
    options: dict[str, Any] = {"enhance": False}
    if rig is not None:
        options.update(_read_rig(rig))
    if frame is not None:
        options["frame_index"] = frame
    if edge_length_mm is not None:
        if not edge_length_mm > 0:
            raise ValueError(f"--edge-length-mm: must be > 0, got {edge_length_mm}")
        options["target_edge_length_m"] = edge_length_mm / 1000.0
    return options


@app.command()
def reconstruct(
    capture: Annotated[Path, typer.Argument(help="Capture directory or .zip (format v1).")],
    out: Annotated[Path, typer.Option("--out", help="Output mesh: .glb (glTF binary, Draco) "
                                      "or .ply.")],
    report: Annotated[Path | None, typer.Option(
        "--report", help="Write a JSON report: stage timings, counts, output size, and "
        "distance figures with --ground-truth.")] = None,
    ground_truth: Annotated[Path | None, typer.Option(
        "--ground-truth", help="Ground-truth mesh in world coordinates (e.g. the "
        "ground_truth.ply of `volumesh synth`) for accuracy figures.")] = None,
    enhance: Annotated[bool, typer.Option(
        "--enhance/--no-enhance", help="Enhancement of the remeshed surface (the LDM). Off by "
        "default: it does not yet improve reconstructions (see the README).")
        ] = False,
    rig: Annotated[Path | None, typer.Option(
        "--rig", help="rig.json whose world_from_depth poses replace the capture's.")] = None,
    frame: Annotated[int | None, typer.Option(
        "--frame", help="Frame index to reconstruct (default: the first).")] = None,
    edge_length_mm: Annotated[float | None, typer.Option(
        "--edge-length-mm", help="Remeshing target edge length, mm (default 12).")] = None,
) -> None:
    """Runs the whole pipeline on one frame of CAPTURE and writes the mesh to OUT."""
    from tqdm import tqdm

    from app.cli.paths import output_file
    from pipeline.io.capture_io import open_capture
    from pipeline.io.gltf_io import write_mesh
    from pipeline.stage_config import config_from_options
    from pipeline.stages import check_capture, planned_stages, posed_cameras
    from pipeline.stages import reconstruct as run_pipeline

    output_file(out, suffixes=(".glb", ".ply"))
    if report is not None:
        output_file(report, "--report")
    config = config_from_options({**_options(rig, frame, edge_length_mm), "enhance": enhance})
    truth = None
    if ground_truth is not None:
        from pipeline.io.mesh_io import read_mesh

        truth = read_mesh(ground_truth)
    with open_capture(capture) as reader:
        check_capture(reader, config)
        bar = tqdm(total=len(planned_stages(config)), desc="reconstruct", unit="stage",
                   leave=False)
        begun: list[str] = []

        def on_stage(name: str) -> None:
            if begun:
                bar.update(1)
            begun.append(name)
            bar.set_description(name)

        with bar:
            mesh, figures = run_pipeline(reader, config, on_stage=on_stage)
            bar.update(1)
        cameras = posed_cameras(reader.meta, config)
    write_mesh(out, mesh)
    figures["output"] = {"path": str(out), "bytes": out.stat().st_size}
    if truth is not None:
        from pipeline.reconstruct.quality import MetricsConfig, compare

        figures["accuracy"] = compare(mesh, truth, cameras, MetricsConfig())
    if report is not None:
        report.write_text(json.dumps(figures, indent=1))
    summary = (f"wrote {out} ({mesh.face_count} triangles, {out.stat().st_size} bytes, "
               f"{figures['total_seconds']:.1f} s)")
    if "accuracy" in figures:
        acc = figures["accuracy"]
        summary += (f"; C2M RMS {acc['result_to_gt']['rms_m'] * 1e3:.2f} mm, "
                    f"{acc['coverage_visible'] * 100:.1f} % of the visible surface within "
                    f"{acc['coverage_threshold_m'] * 1e3:.0f} mm")
    typer.echo(summary)
