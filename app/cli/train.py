"""`volumesh train`: trains the twicing selector (the pre-smoothing), the regressor, the VAE and
the U-Net + ControlNet, fine-tunes the three end to end, then the vertex gains of the mesh
update (`pipeline.enhance.training.run`); or makes weights from trained ones (`--average`,
`--selector-ensemble`). Writes weights and training.json into --out."""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated

import typer

from app.cli import app

STAGES = "selector,regressor,vae,ldm,finetune,gain"
MESHES = Path("../shared/data/meshes")
MESH_SUFFIXES = (".obj", ".ply", ".off")


@app.command()
def train(
    out: Annotated[Path, typer.Option("--out", help="Directory for checkpoints and weights.")],
    config: Annotated[str, typer.Option("--config", help="tiny | small | large")] = "small",
    resume: Annotated[bool, typer.Option("--resume", help="Continue from --out.")] = False,
    device: Annotated[str, typer.Option("--device", help="auto | cpu | cuda")] = "auto",
    seed: Annotated[int, typer.Option("--seed")] = 0,
    stages: Annotated[str, typer.Option("--stages", help="Comma-separated.")] = STAGES,
    meshes: Annotated[Path, typer.Option("--meshes", help="Folder of source meshes.")] = MESHES,
    procedural: Annotated[int, typer.Option("--procedural", help="Procedural shapes.")] = 6,
    budget_scale: Annotated[
        float, typer.Option("--budget-scale", help="Multiply every stage's steps and minutes.")
    ] = 1.0,
    workers: Annotated[
        int, typer.Option("--workers", min=1, help="Processes making the training pairs.")
    ] = 1,
    minutes: Annotated[float | None, typer.Option(
        "--minutes", min=0.01, help="Wall-clock cap per network stage (default: the config's).",
    )] = None,
    poses: Annotated[int | None, typer.Option(
        "--poses", min=1, help="Poses per source mesh (default: the config's).")] = None,
    mix: Annotated[str, typer.Option(
        "--mix", help="Degradation mix of the pairs: full (every degradation) or mesh (only "
        "what a mesh's renders carry, as the enhance stage meets).")] = "full",
    lr: Annotated[float | None, typer.Option(
        "--lr", min=1e-7, max=1.0, help="Peak learning rate of every network stage (default: "
        "the config's; fine-tuning --init weights wants less, e.g. 2e-4).")] = None,
    loss_mask: Annotated[float | None, typer.Option(
        "--loss-mask", min=0.001, max=1.0, help="Leave pixels where an input is further than "
        "this (normalised depth) from the clean render out of the losses (default: the "
        "config's, 0.05; 0.02 leaves out all that sees another surface).")] = None,
    noise: Annotated[str | None, typer.Option(
        "--noise", help="Comma-separated noise models the noisy meshes draw from: uniform, "
        "gaussian, laplace (default: all three).")] = None,
    init: Annotated[Path | None, typer.Option(
        "--init", help="Fine-tune the weights in this folder (e.g. the shipped ones): the "
        "regressor stage starts from its regressor.safetensors, the finetune stage from its "
        "vae/ldm.safetensors (then leave out the vae and ldm stages).")] = None,
    average: Annotated[tuple[Path, Path] | None, typer.Option(
        "--average", metavar="START END", help="Train nothing: write into a new --out END's "
        "weights with its regressor, VAE and LDM moved --share of the way from START's "
        "(the folder a --init run started from) to END's (WiSE-FT).")] = None,
    share: Annotated[float, typer.Option(
        "--share", min=0.0, max=1.0, help="With --average: END's share.")] = 0.5,
    selector_ensemble: Annotated[list[Path] | None, typer.Option(
        "--selector-ensemble", help="Train nothing: write --out/selector.safetensors, the "
        "ensemble (mean blend weights) of these selector files of runs with different seeds; "
        "give it once per file.")] = None,
) -> None:
    """Train the enhancement models from meshes (never the bunny: it is the test model)."""
    if average is not None and selector_ensemble:
        raise ValueError("--average and --selector-ensemble: give one of them")
    if average is not None:
        return _write_average(*average, share, out)
    if selector_ensemble:
        return _write_selector_ensemble(selector_ensemble, out)
    from app.cli.paths import output_folder
    from pipeline.enhance.device import resolve_device
    from pipeline.enhance.training.plan import run_config, wanted_stages
    from pipeline.enhance.training.run import RunSettings, train_run

    cfg = run_config(config, budget_scale, poses, mix, minutes, lr, loss_mask, noise)
    init_store = None if init is None else FolderStore(init)
    wanted = wanted_stages(stages, init_store)
    if not meshes.is_dir():  # an empty folder is fine: procedural shapes alone
        raise ValueError(f"--meshes: {meshes} is not a folder")
    settings = RunSettings(cfg, wanted, seed, resolve_device(device), resume, workers,
                           procedural)
    train_run(settings, _source_meshes(meshes), FolderStore(output_folder(out)), init_store,
              stage_bar, lambda stage, figures: typer.echo(f"{stage}: {json.dumps(figures)}"))


@app.command("interpolate-weights", hidden=True, add_help_option=False,
             context_settings={"allow_extra_args": True, "ignore_unknown_options": True})
def interpolate_weights() -> None:
    """Removed: `volumesh train --average`."""
    raise ValueError("interpolate-weights: removed; use `volumesh train --average START END "
                     "--out NEW [--share S]`")


@app.command("selector-ensemble", hidden=True, add_help_option=False,
             context_settings={"allow_extra_args": True, "ignore_unknown_options": True})
def removed_selector_ensemble() -> None:
    """Removed: `volumesh train --selector-ensemble`."""
    raise ValueError("selector-ensemble: removed; use `volumesh train --selector-ensemble A "
                     "--selector-ensemble B [...] --out DIR`")


class FolderStore:
    """A folder as a run's `WeightsStore`."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.where = str(folder)

    def names(self) -> list[str]:
        return sorted(p.name for p in self.folder.iterdir() if p.is_file())

    def has(self, name: str) -> bool:
        return (self.folder / name).is_file()

    def read(self, name: str) -> bytes:
        return (self.folder / name).read_bytes()

    def write(self, name: str, data: bytes) -> None:
        path = self.folder / name
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f"{path.name}.tmp")
        tmp.write_bytes(data)
        os.replace(tmp, path)  # atomic: an interrupted write never spoils the last one


@contextmanager
def stage_bar(stage: str) -> Iterator:
    """A progress bar for a stage of the run, and the (fraction, text) callback that moves it."""
    from tqdm import tqdm

    bar = tqdm(total=1000, desc=stage)

    def moved(fraction: float, text: str) -> None:
        bar.n = int(fraction * 1000)
        bar.set_postfix_str(text, refresh=False)
        bar.refresh()

    try:
        yield moved
    finally:
        bar.close()


def _source_meshes(folder: Path) -> list:
    """(name, mesh) of the folder's mesh files, by name."""
    from pipeline.io.mesh_io import read_mesh

    paths = sorted(p for p in folder.glob("*") if p.suffix.lower() in MESH_SUFFIXES)
    return [(p.stem, read_mesh(p)) for p in paths]


def _write_average(start: Path, end: Path, share: float, out: Path) -> None:
    """`--average`: the averaged weights into the new folder `out`."""
    from app.cli.paths import output_folder

    for folder in (start, end):
        if not folder.is_dir():
            raise ValueError(f"--average: {folder} is not a folder")
    if out.exists():
        raise ValueError(f"--out: {out} exists (give a new folder)")
    output_folder(out.parent)
    # torch loads with the merge: only once the arguments are known to be good.
    from pipeline.enhance.training.merge import averaged_weights

    files = averaged_weights(FolderStore(start), FolderStore(end), share)
    out.mkdir()
    for name, data in files.items():
        (out / name).write_bytes(data)


def _write_selector_ensemble(members: list[Path], out: Path) -> None:
    """`--selector-ensemble`: the ensemble of the member files into `out`/selector.safetensors."""
    from app.cli.paths import output_folder

    for path in members:
        if not path.is_file():
            raise ValueError(f"--selector-ensemble: {path} is not a file")
    from pipeline.enhance.training.merge import selector_ensemble

    data = selector_ensemble([(str(p), p.read_bytes()) for p in members])
    FolderStore(output_folder(out)).write("selector.safetensors", data)
