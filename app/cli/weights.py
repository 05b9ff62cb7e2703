"""`volumesh interpolate-weights`: a weights folder whose depth networks lie between two
trainings of them (WiSE-FT); how the shipped weights of the twenty-third session were made."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Annotated

import typer

from app.cli import app

DEPTH_NETWORKS = ("regressor", "vae", "ldm")


@app.command("interpolate-weights")
def interpolate_weights(
    start: Annotated[Path, typer.Argument(help="Weights folder fine-tuned from (e.g. the "
                                          "shipped one before a `--init` run).")],
    end: Annotated[Path, typer.Argument(help="Weights folder of the fine-tuning run.")],
    out: Annotated[Path, typer.Option("--out", help="New folder for the weights.")],
    share: Annotated[float, typer.Option(
        "--share", min=0.0, max=1.0,
        help="Share of END in the depth networks' weights.")] = 0.5,
) -> None:
    """Write END's weights with its regressor, VAE and LDM moved to `share` of the way from
    START's to END's, tensor by tensor (float16); END's other .safetensors (selector, vertex
    gains) are copied as they are."""
    from app.cli.paths import output_folder
    from pipeline.enhance.weights.loading import interpolated_weights

    for folder in (start, end):
        missing = [n for n in DEPTH_NETWORKS if not (folder / f"{n}.safetensors").is_file()]
        if missing:
            raise ValueError(f"interpolate-weights: {folder} has no "
                             f"{', '.join(missing)}.safetensors")
    if out.exists():
        raise ValueError(f"interpolate-weights: --out: {out} exists (give a new folder)")
    output_folder(out.parent, "interpolate-weights: --out")
    interpolated = {}
    for name in DEPTH_NETWORKS:
        try:
            interpolated[name] = interpolated_weights(
                (start / f"{name}.safetensors").read_bytes(),
                (end / f"{name}.safetensors").read_bytes(), share)
        except Exception as exc:  # whatever a foreign file makes `weights_from_bytes` raise
            raise ValueError(f"interpolate-weights: {name}.safetensors of {start} and {end}: "
                             f"{exc}") from None
    out.mkdir()
    for name, data in interpolated.items():
        (out / f"{name}.safetensors").write_bytes(data)
    for path in sorted(end.glob("*.safetensors")):
        if path.stem not in DEPTH_NETWORKS:
            shutil.copy(path, out / path.name)
