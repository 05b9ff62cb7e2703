"""`volumesh enhance-mesh`: LDM (or baseline) enhancement of one mesh file."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from app.cli import app
from pipeline.enhance.presmooth.midrange import BoundedNoiseConfig
from pipeline.enhance.self_check import SelfCheck
from pipeline.enhance.update.normal_filter import NormalFilterConfig


@app.command("enhance-mesh")
def enhance_mesh_command(
    mesh_in: Annotated[
        Path, typer.Argument(metavar="IN", help="Mesh to enhance (.ply, .obj, ...).")
    ],
    out: Annotated[Path, typer.Option("--out", help="Output mesh: .glb (glTF binary, Draco) "
                                      "or .ply.")],
    method: Annotated[
        str,
        typer.Option(
            "--method",
            help="ldm|regressor|views|taubin|laplacian|twicing|adaptive|selector|bilateral",
        ),
    ] = "ldm",
    views: Annotated[int, typer.Option("--views", help="Depth views (six axis views first).")] = 6,
    resolution: Annotated[
        int, typer.Option("--resolution", help="Depth image side, pixels.")
    ] = 256,
    steps: Annotated[int, typer.Option("--steps", help="DDIM steps (1 = one-step mode).")] = 4,
    strength: Annotated[
        float, typer.Option("--strength", help="Start point in the noise schedule.")
    ] = 0.5,
    iterations: Annotated[
        int, typer.Option("--iterations", help="Iterations of classical smoothers.")
    ] = 8,
    presmooth: Annotated[
        int,
        typer.Option(
            "--presmooth",
            help="Laplacian iterations before the networks (as the weights were trained).",
        ),
    ] = 30,
    presmooth_passes: Annotated[
        int,
        typer.Option(
            "--presmooth-passes",
            help="Passes of that smoothing, 2 = twicing (as the weights were trained).",
        ),
    ] = 2,
    adaptive: Annotated[
        bool,
        typer.Option(
            "--adaptive-presmooth/--fixed-presmooth",
            help="Choose the pre-smoothing's count per vertex (--presmooth is the pilot's).",
        ),
    ] = True,
    learned: Annotated[
        bool,
        typer.Option(
            "--learned-presmooth/--no-learned-presmooth",
            help="The pre-smoothing is the trained selector's blend of twicings (then "
            "--presmooth 0 still turns it off, and its passes and pilot are the weights').",
        ),
    ] = True,
    bounded_rings: Annotated[
        int,
        typer.Option(
            "--bounded-rings",
            help="Rings of neighbours whose residual range ends the pre-smoothing where the "
            "noise is bounded (light-tailed); 0: off.",
        ),
    ] = BoundedNoiseConfig.rings,
    gain: Annotated[
        float | None,
        typer.Option("--gain", help="Follow this fixed share (0, 2] of the networks' depth "
                     "correction everywhere, instead of the learned per-vertex gains."),
    ] = None,
    min_noise_ratio: Annotated[
        float,
        typer.Option(
            "--min-noise-ratio",
            help="The networks leave a mesh less noisy than this (noise over mean edge "
            "length) unchanged; 0 always enhances.",
        ),
    ] = 0.05,
    normal_filter: Annotated[
        int,
        typer.Option(
            "--normal-filter",
            help="Rounds of bilateral normal filtering that end the view-based update; 0: off.",
        ),
    ] = NormalFilterConfig.normal_iterations,
    remesh_ahead: Annotated[
        bool | None,
        typer.Option(
            "--remesh-ahead/--remesh-after",
            help="Start the light remesh on the mesh the update moves, beside the networks, "
            "and carry it onto the moved mesh (faster where a GPU runs the networks; up to "
            "0.2 %% more C2M RMS on the benchmark's meshes), or remesh the moved mesh after "
            "the update. Default: ahead on a GPU, after on the CPU.",
        ),
    ] = None,
    self_check: Annotated[
        bool,
        typer.Option(
            "--self-check/--no-self-check",
            help="Before the networks' update, enhance a simulated copy of the mesh (the "
            "classical result with the mesh's own noise shuffled back on) with and without "
            "them, and keep the classical result where they lose there. About doubles the "
            "time.",
        ),
    ] = False,
    seed: Annotated[int, typer.Option("--seed")] = 0,
    ensemble: Annotated[
        int, typer.Option("--ensemble", help="Flipped copies of each view averaged: 1|2|4|8.")
    ] = 1,
    device: Annotated[str, typer.Option("--device", help="auto | cpu | cuda")] = "auto",
    weights: Annotated[
        Path | None,
        typer.Option(
            "--weights", help="Folder of .safetensors (regressor, vae, ldm, selector, "
            "ldm_gain, regressor_gain; those it lacks: the shipped)."
        ),
    ] = None,
) -> None:
    """Enhance a mesh: render depth views, enhance them, move vertices to the enhanced depth."""
    import time

    from tqdm import tqdm

    from app.cli.paths import output_file
    from pipeline.enhance import EnhanceConfig, enhance_mesh
    from pipeline.enhance.config import validate_config
    from pipeline.enhance.enhancement import gated, past_the_gate, skipped_at
    from pipeline.enhance.noise_level import noise_to_edge_ratio
    from pipeline.enhance.weights import DEFAULT_FILES
    from pipeline.io.gltf_io import write_mesh
    from pipeline.io.mesh_io import read_mesh

    output_file(out, suffixes=(".glb", ".ply"))
    loaded = None
    if weights is not None:
        if not weights.is_dir():
            raise ValueError(f"--weights: {weights} is not a directory")
        loaded = {
            p.stem: p.read_bytes()
            for p in weights.glob("*.safetensors")
            if p.stem in DEFAULT_FILES
        }
    config = EnhanceConfig(
        method=method,
        views=views,
        resolution=resolution,
        steps=steps,
        strength=strength,
        seed=seed,
        ensemble=ensemble,
        iterations=iterations,
        presmooth_iterations=presmooth,
        presmooth_passes=presmooth_passes,
        presmooth_adaptive=adaptive,
        presmooth_learned=learned,
        bounded_noise=BoundedNoiseConfig(rings=bounded_rings),
        correction_gain=EnhanceConfig.correction_gain if gain is None else gain,
        learned_gain=gain is None,
        min_noise_ratio=min_noise_ratio,
        self_check=self_check,
        normal_filter=NormalFilterConfig(normal_iterations=normal_filter),
        remesh_ahead=remesh_ahead,
        device=device,
        weights=loaded,
    )
    validate_config(config)
    mesh = read_mesh(mesh_in)
    noise_ratio = noise_to_edge_ratio(mesh) if gated(config) else None
    skipped = noise_ratio is not None and skipped_at(noise_ratio, config)
    if skipped:
        typer.echo(
            f"enhance-mesh: {mesh_in}'s estimated noise, {noise_ratio:.3f} of its "
            f"edge length, is below --min-noise-ratio {min_noise_ratio}: written unchanged",
            err=True,
        )
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


def _told(check: SelfCheck) -> str:
    """The self-check's decision and its figures, one line."""
    kept = ("the networks' update kept" if check.networks_help else
            "the classical result kept (the networks lost)")
    return (f"enhance-mesh: self-check on a simulated copy: C2M RMS "
            f"{check.with_networks_rms_m * 1e3:.4f} mm with the networks, "
            f"{check.without_networks_rms_m * 1e3:.4f} mm without; {kept}")
