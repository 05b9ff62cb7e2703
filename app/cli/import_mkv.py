"""`volumesh import-mkv`: Azure Kinect recordings (k4arecorder .mkv) to a capture."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from app.cli import app


@app.command("import-mkv")
def import_mkv(
    recordings: Annotated[list[Path], typer.Argument(
        help="k4arecorder recordings (.mkv), one per device of the rig.")],
    out: Annotated[Path, typer.Option("--out", help="Capture to write: a directory, or a .zip "
                                      "when it ends in .zip.")],
    sync_window_us: Annotated[int | None, typer.Option(
        "--sync-window-us", help="Frames of one frame-set lie within this of its earliest, "
        "microseconds (default: half a frame period).")] = None,
    target: Annotated[Path | None, typer.Option(
        "--target", help="For a calibration recording: a JSON file with the ChArUco target "
        "the colour images show (what capture.json's \"target\" holds).")] = None,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace OUT if it "
                                            "exists.")] = False,
) -> None:
    """Writes the recordings of one rig as a capture with many frames (no poses).

    Frames are matched across devices by device timestamp; intrinsics and colour-from-depth
    come from each device's calibration. Calibrate a calibration recording imported the same
    way for the poses.
    """
    from tqdm import tqdm

    from pipeline.io.k4a_import import (
        ImportConfig,
        import_recordings,
        open_recordings,
        read_target,
    )

    _check_out(out, overwrite)
    config = ImportConfig(sync_window_us=sync_window_us,
                          target=read_target(target) if target is not None else None)
    opened = open_recordings(recordings, config)
    staging = _staging_folder(out)
    try:
        with tqdm(total=100, desc="import-mkv", unit="%") as bar:
            def advance(fraction: float) -> None:
                bar.update(max(0, round(fraction * 100) - bar.n))

            report = import_recordings(opened, staging, progress=advance)
        _publish(staging, out)
    finally:
        _remove(staging)
    seconds = report.frame_sets * report.frame_period_us / 1e6
    typer.echo(f"wrote {out}: {len(report.camera_ids)} camera(s) ({', '.join(report.camera_ids)})"
               f", {report.frame_sets} frame-set(s), {seconds:.1f} s at "
               f"{round(1e6 / report.frame_period_us)} fps, sync window "
               f"{report.sync_window_us} us")
    if report.dropped:
        missing = ", ".join(f"{cam} {n}" for cam, n in report.dropped_by_camera.items() if n)
        typer.echo(f"skipped {report.dropped} incomplete frame-set(s), frames missing from: "
                   f"{missing}")
    if report.outside:
        typer.echo(f"skipped {report.outside} frame-set(s) outside the time every recording "
                   "covers")
    if report.missing_color:
        typer.echo(f"{report.missing_color} frame(s) without their colour image")
    if target is None:
        typer.echo("no camera poses: import a calibration recording the same way with its "
                   "--target, run `volumesh calibrate` on it, and reconstruct with that rig "
                   "(--rig)")
    for warning in report.warnings:
        typer.echo(f"warning: {warning}", err=True)


def _check_out(out: Path, overwrite: bool) -> None:
    """ValueError where OUT exists and may not be replaced."""
    if not out.exists():
        return
    if not overwrite:
        raise ValueError(f"--out: {out} exists (pass --overwrite)")
    is_capture = (out / "capture.json").is_file() if out.is_dir() else out.suffix == ".zip"
    if not is_capture:
        raise ValueError(f"--out: {out} is not a capture; --overwrite only replaces one")


def _staging_folder(out: Path) -> Path:
    """An empty folder beside OUT to write into, so that OUT appears only when complete."""
    import tempfile

    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        return Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    except OSError as exc:
        raise ValueError(f"--out: cannot write beside {out} ({exc.strerror})") from exc


def _publish(staging: Path, out: Path) -> None:
    """Moves the finished capture to OUT (a folder, or packed as a zip)."""
    import os

    from pipeline.io.capture_io import zip_capture

    if out.suffix.lower() == ".zip":
        packed = staging.with_name(staging.name + ".zip")
        try:
            zip_capture(staging, packed)
            os.replace(packed, out)
        finally:
            _remove(packed)
        return
    if out.exists():
        _remove(out)
    staging.rename(out)


def _remove(path: Path) -> None:
    import shutil

    if path.is_dir():
        shutil.rmtree(path, ignore_errors=True)
    elif path.exists():
        path.unlink()
