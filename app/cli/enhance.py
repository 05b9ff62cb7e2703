"""`volumesh enhance-mesh`: enhancement of one mesh file (regressor, ldm or classical)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from app.cli import app

if TYPE_CHECKING:
    from pipeline.enhance.self_check import SelfCheck

_GONE_WITH_SETTING = {
    "--iterations": "iterations",
    "--presmooth": "presmooth_iterations",
    "--presmooth-passes": "presmooth_passes",
    "--adaptive-presmooth/--fixed-presmooth": "presmooth_adaptive",
    "--learned-presmooth/--no-learned-presmooth": "presmooth_learned",
    "--gain": "correction_gain",
    "--ensemble": "ensemble",
}
"""Options that set an enhancement setting jobs may no longer set either: refused with the
job setting's own line (`pipeline.enhance.config.REMOVED_SETTINGS`)."""
_REPLACED = {
    "--views": "removed; enhance-mesh renders the six axis views the networks were trained on "
               "(a job's enhancement.views still sets it)",
    "--resolution": "removed; enhance-mesh renders views of the side the networks were trained "
                    "on (a job's enhancement.resolution still sets it)",
    "--strength": "removed; enhance-mesh samples at the strength the LDM was fine-tuned with "
                  "(a job's enhancement.strength still sets it)",
    "--bounded-rings": "removed; the midrange estimator reads the rings it was tuned with",
    "--min-noise-ratio": "removed; the noise gate is the enhancement's own (a mesh less noisy "
                         "than 0.05 of its edge length is written unchanged)",
    "--normal-filter": "removed; the bilateral normal filter ends every method as tuned",
    "--remesh-ahead/--remesh-after": "removed; the speculative remesh runs where the device is "
                                     "a GPU, the remesh after the update on the CPU",
}
REMOVED_OPTIONS = (*_REPLACED, *_GONE_WITH_SETTING)
"""Options `enhance-mesh` refuses, each with what takes its place (`removed_reason`): given,
they fail with that line rather than be silently accepted."""


def removed_reason(declaration: str) -> str:
    """What took the place of a removed option."""
    if declaration in _GONE_WITH_SETTING:
        # Read only when refusing: the enhancement's modules load in about half a second,
        # which every other command would pay at start.
        from pipeline.enhance.config import REMOVED_SETTINGS

        return f"removed; {REMOVED_SETTINGS[_GONE_WITH_SETTING[declaration]]}"
    return _REPLACED[declaration]


def _refused(declaration: str) -> Any:
    """A hidden option that fails naming what replaced it (`removed_reason`) when given."""
    names = declaration.split("/")

    def refuse(value: Any) -> None:
        if value is not None:
            raise ValueError(f"{declaration}: {removed_reason(declaration)}")

    return typer.Option(*names if len(names) == 1 else [declaration], hidden=True,
                        callback=refuse)


@app.command("enhance-mesh")
def enhance_mesh_command(
    mesh_in: Annotated[
        Path, typer.Argument(metavar="IN", help="Mesh to enhance (.ply, .obj, ...).")
    ],
    out: Annotated[Path, typer.Option("--out", help="Output mesh: .glb (glTF binary, Draco) "
                                      "or .ply.")],
    method: Annotated[str, typer.Option(
        "--method", help="regressor | ldm (a network corrects the pre-smoothed mesh's depth "
        "views) | classical (the same pre-smoothing and ending, no network).")] = "regressor",
    steps: Annotated[int, typer.Option(
        "--steps", help="DDIM steps of the LDM (1 = one-step mode).")] = 4,
    self_check: Annotated[bool, typer.Option(
        "--self-check/--no-self-check",
        help="Before the networks' update, enhance a simulated copy of the mesh (the "
        "classical result with the mesh's own noise shuffled back on) with and without "
        "them, and keep the classical result where they lose there. About doubles the "
        "time.")] = False,
    device: Annotated[str, typer.Option("--device", help="auto | cpu | cuda")] = "auto",
    weights: Annotated[Path | None, typer.Option(
        "--weights", help="Folder of .safetensors (regressor, vae, ldm, selector, ldm_gain, "
        "regressor_gain; those it lacks: the shipped).")] = None,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the LDM's start noise.")] = 0,
    views: Annotated[str | None, _refused("--views")] = None,
    resolution: Annotated[str | None, _refused("--resolution")] = None,
    strength: Annotated[str | None, _refused("--strength")] = None,
    iterations: Annotated[str | None, _refused("--iterations")] = None,
    presmooth: Annotated[str | None, _refused("--presmooth")] = None,
    presmooth_passes: Annotated[str | None, _refused("--presmooth-passes")] = None,
    adaptive: Annotated[bool | None, _refused("--adaptive-presmooth/--fixed-presmooth")] = None,
    learned: Annotated[bool | None,
                       _refused("--learned-presmooth/--no-learned-presmooth")] = None,
    bounded_rings: Annotated[str | None, _refused("--bounded-rings")] = None,
    gain: Annotated[str | None, _refused("--gain")] = None,
    min_noise_ratio: Annotated[str | None, _refused("--min-noise-ratio")] = None,
    normal_filter: Annotated[str | None, _refused("--normal-filter")] = None,
    remesh_ahead: Annotated[bool | None, _refused("--remesh-ahead/--remesh-after")] = None,
    ensemble: Annotated[str | None, _refused("--ensemble")] = None,
) -> None:
    """Enhance a mesh: pre-smooth it, correct its depth views with a network, move the
    vertices to the corrected depth and light-remesh it."""
    import time

    from tqdm import tqdm

    from app.cli.paths import output_file
    from pipeline.enhance import EnhanceConfig, enhance_mesh
    from pipeline.enhance.config import validate_config
    from pipeline.enhance.noise_level import (
        gated,
        noise_to_edge_ratio,
        past_the_gate,
        skipped_at,
    )
    from pipeline.io.gltf_io import write_mesh
    from pipeline.io.mesh_io import read_mesh

    output_file(out, suffixes=(".glb", ".ply"))
    config = EnhanceConfig(method=method, steps=steps, seed=seed, self_check=self_check,
                           device=device, weights=_weights(weights))
    validate_config(config)
    mesh = read_mesh(mesh_in)
    noise_ratio = noise_to_edge_ratio(mesh) if gated(config) else None
    skipped = noise_ratio is not None and skipped_at(noise_ratio, config)
    if skipped:
        typer.echo(f"enhance-mesh: {mesh_in}'s estimated noise, {noise_ratio:.3f} of its edge "
                   f"length, is below the noise gate, {config.min_noise_ratio}: written "
                   "unchanged", err=True)
    checks: list[SelfCheck] = []
    started = time.perf_counter()
    with tqdm(total=100, desc="enhance", unit="%") as bar:

        def progress(fraction: float) -> None:
            bar.n = int(fraction * 100)
            bar.refresh()

        # By the decision just told, either way.
        result = mesh if skipped else enhance_mesh(mesh, past_the_gate(config), progress,
                                                   on_check=checks.append)
        progress(1.0)
    for check in checks:
        typer.echo(_told(check), err=True)
    write_mesh(out, result)
    typer.echo(f"wrote {out} ({result.vertex_count} vertices, {result.face_count} triangles, "
               f"{out.stat().st_size} bytes; {method}, {time.perf_counter() - started:.1f} s)")


def _weights(folder: Path | None) -> dict[str, bytes] | None:
    """The model files of a --weights folder by name (None: the shipped)."""
    from pipeline.enhance.weights import DEFAULT_FILES

    if folder is None:
        return None
    if not folder.is_dir():
        raise ValueError(f"--weights: {folder} is not a directory")
    return {p.stem: p.read_bytes() for p in folder.glob("*.safetensors")
            if p.stem in DEFAULT_FILES}


def _told(check: SelfCheck) -> str:
    """The self-check's decision and its figures, one line."""
    kept = ("the networks' update kept" if check.networks_help else
            "the classical result kept (the networks lost)")
    return (f"enhance-mesh: self-check on a simulated copy: C2M RMS "
            f"{check.with_networks_rms_m * 1e3:.4f} mm with the networks, "
            f"{check.without_networks_rms_m * 1e3:.4f} mm without; {kept}")
