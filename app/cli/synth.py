"""`volumesh synth`: a synthetic capture of a mesh by the simulated 8-camera Azure Kinect rig."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from app.cli import app


@app.command()
def synth(
    out: Annotated[Path, typer.Option("--out", help="Capture directory to write.")],
    mesh: Annotated[str | None, typer.Option("--mesh", help="Mesh file (OBJ, PLY, ...), or "
                                             "'sample' for the built-in subject.")] = None,
    target: Annotated[str | None, typer.Option(
        "--target", help="Instead of a mesh, a ChArUco calibration capture: 'plane' (one "
        "board moved through the volume) or 'cube' (a board on each face).")] = None,
    height_m: Annotated[float, typer.Option("--height-m", help="Subject height, metres.")] = 1.8,
    max_radius_m: Annotated[float, typer.Option(
        "--max-radius-m", help="Scale wide models down to this horizontal radius, metres "
        "(0: never).")] = 1.1,
    up_axis: Annotated[str, typer.Option("--up-axis", help="The mesh's up axis: "
                                         "+x -x +y -y +z -z.")] = "+y",
    seed: Annotated[int, typer.Option("--seed", help="Seed of noise and pose errors.")] = 0,
    cameras: Annotated[int, typer.Option("--cameras", help="Number of cameras "
                                         "(two rings).")] = 8,
    pose_error_deg: Annotated[float, typer.Option(
        "--pose-error-deg", help="Rotation error of each written pose, degrees.")] = 0.0,
    pose_error_mm: Annotated[float, typer.Option(
        "--pose-error-mm", help="Position error of each written pose, mm.")] = 0.0,
    no_noise: Annotated[bool, typer.Option("--no-noise", help="Ideal depth, no sensor "
                                           "noise.")] = False,
    frames: Annotated[int | None, typer.Option("--frames", help="Frames per camera (default 1, "
                                               "24 with --target).")] = None,
    floor: Annotated[bool, typer.Option("--floor", help="Render a floor plane too.")] = False,
    motion: Annotated[str, typer.Option(
        "--motion", help="The subject over the frames: static (noise drawn anew each frame), "
        "rigid (turning and swaying) or articulated (bowing at the waist); truth_poses.json "
        "gives its pose and bend per frame.")] = "static",
    fps: Annotated[float, typer.Option("--fps", help="Frame rate of the capture's "
                                       "timestamps, frames per second.")] = 30.0,
    zip_: Annotated[bool, typer.Option("--zip", help="Also pack the capture as "
                                       "OUT.zip.")] = False,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace OUT if it "
                                            "exists.")] = False,
) -> None:
    """Writes a synthetic capture to OUT, and beside it in OUT the ground-truth mesh
    (ground_truth.ply, world frame) and the true camera poses (true_rig.json, rig.json form).
    With --motion rigid or articulated, truth_poses.json holds the subject's pose in each frame
    and its bend (frame f's truth is ground_truth.ply bent by bow_rad[f] about the horizontal
    x axis at joint_y_m, faded in over joint_blend_m, then moved by world_from_subject[f];
    `pipeline.synth.motion.SequenceTruth.mesh`).
    """
    import json
    import shutil

    import numpy as np
    from tqdm import tqdm

    from app.cli.paths import output_folder
    from pipeline.io.capture_io import write_capture, zip_capture
    from pipeline.io.mesh_io import read_mesh, write_ply
    from pipeline.synth.motion import MOTIONS, MotionConfig, synthesize_sequence
    from pipeline.synth.scene import SynthConfig, sample_mesh, true_cameras

    if (mesh is None) == (target is None):
        raise ValueError("--mesh / --target: give exactly one of them")
    if motion not in MOTIONS:
        raise ValueError(f"--motion: must be one of {', '.join(MOTIONS)}, got {motion!r}")
    frames = frames if frames is not None else (24 if target is not None else 1)
    config = SynthConfig(model_height_m=height_m, max_radius_m=max_radius_m or None,
                         up_axis=up_axis, seed=seed, camera_count=cameras,
                         pose_error_rot_deg=pose_error_deg,
                         pose_error_trans_m=pose_error_mm / 1000.0, noise=not no_noise,
                         frame_count=frames, floor=floor)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        if not overwrite:
            raise ValueError(f"--out: {out} exists and is not empty (pass --overwrite)")
        if not (out / "capture.json").is_file():
            raise ValueError(f"--out: {out} holds no capture.json; --overwrite only replaces "
                             "a capture directory")
        shutil.rmtree(out)
    output_folder(out.parent)
    if target is not None:
        _synth_target(out, target, frames, cameras, seed, not no_noise, zip_)
        return
    assert mesh is not None
    source = sample_mesh() if mesh == "sample" else read_mesh(mesh)
    with tqdm(total=cameras, desc="synth", unit="camera") as bar:
        def advance(fraction: float) -> None:
            bar.update(round(fraction * cameras) - bar.n)

        sequence = synthesize_sequence(source, config, MotionConfig(kind=motion,
                                                                   frame_rate_hz=fps),
                                       progress=advance)
        meta, views, truth = sequence
        write_capture(out, meta, views)
    ground_truth = truth.subject
    if zip_:  # before the ground truth, so the zip holds the capture alone
        zip_path = out.with_name(out.name + ".zip")
        zip_capture(out, zip_path)
        typer.echo(f"wrote {zip_path}")
    write_ply(out / "ground_truth.ply", ground_truth)
    poses = {cam.id: np.asarray(cam.world_from_depth).tolist()
             for cam in true_cameras(ground_truth, config)}
    (out / "true_rig.json").write_text(json.dumps({"world_from_depth": poses}, indent=1))
    if motion != "static":
        bows = None if truth.bow_rad is None else truth.bow_rad.round(9).tolist()
        (out / "truth_poses.json").write_text(json.dumps({
            "fps": fps, "world_from_subject": truth.world_from_subject.round(9).tolist(),
            "bow_rad": bows, "joint_y_m": truth.joint_y_m, "joint_blend_m": truth.joint_blend_m}))
    height = float(ground_truth.vertices_m[:, 1].max())
    typer.echo(f"wrote {out} ({cameras} cameras, {frames} frame(s) at {fps:g} fps, {motion} "
               f"subject {height:.2f} m tall), ground_truth.ply and true_rig.json")


def _synth_target(out: Path, kind: str, frames: int, cameras: int, seed: int, noise: bool,
                  zip_: bool) -> None:
    """A calibration capture of a moving ChArUco target, true_rig.json beside it."""
    from tqdm import tqdm

    from pipeline.io.capture_io import write_capture, zip_capture
    from pipeline.io.rig_io import write_rig
    from pipeline.synth.target import TargetSynthConfig, synthesize_calibration

    config = TargetSynthConfig(kind=kind, frame_count=frames, camera_count=cameras, seed=seed,
                               depth_noise=noise)
    with tqdm(total=frames, desc="synth", unit="frame") as bar:
        def advance(fraction: float) -> None:
            bar.update(round(fraction * frames) - bar.n)

        meta, views, truth = synthesize_calibration(config, progress=advance)
        write_capture(out, meta, views)
    if zip_:
        zip_capture(out, out.with_name(out.name + ".zip"))
        typer.echo(f"wrote {out.with_name(out.name + '.zip')}")
    write_rig(out / "true_rig.json", truth)
    typer.echo(f"wrote {out} ({cameras} cameras, {frames} frames of a {kind} ChArUco target) "
               "and true_rig.json")
