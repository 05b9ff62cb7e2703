"""`EnhanceConfig`: how `enhancement.enhance_mesh` enhances a mesh, and its checks."""

from __future__ import annotations

from dataclasses import dataclass, field

from pipeline.enhance.presmooth.midrange import BoundedNoiseConfig
from pipeline.enhance.update.normal_filter import NormalFilterConfig
from pipeline.enhance.update.steps import UpdateConfig

METHODS = (
    "ldm", "regressor", "views", "taubin", "laplacian", "twicing", "adaptive", "selector",
    "bilateral",
)


@dataclass(frozen=True)
class EnhanceConfig:
    """How to enhance a mesh."""

    method: str = "ldm"
    """ldm | regressor | views (raw renders into the update) | taubin | laplacian | twicing |
    adaptive (twicing, its count chosen per vertex) | selector (a learned per-vertex blend of
    twicings, `selector_presmoothed`) | bilateral."""
    views: int = 6
    """Number of depth views (the six axis views first)."""
    resolution: int = 256
    """Depth image side in pixels."""
    steps: int = 4
    """DDIM steps of the LDM (1 = one-step mode)."""
    strength: float = 0.5
    """How far into the noise schedule sampling starts from the degraded latent (0, 1]."""
    seed: int = 0
    """Seed of the LDM's start noise."""
    ensemble: int = 1
    """Geometric self-ensemble: the network runs on this many flips/transposes of each view
    (1, 2, 4 or 8) and the results, turned back, are averaged."""
    iterations: int = 8
    """Iterations of the classical smoothers."""
    presmooth_iterations: int = 30
    """Laplacian smoothing iterations before the networks (ldm, regressor), per pass (the
    pilot's count when adaptive): they correct the smoothed mesh's renders, reading the
    mesh's own as a side input, and the smoothed mesh's vertices move. Should match the
    weights' training (`DataConfig.presmooth_iterations`)."""
    presmooth_passes: int = 2
    """Passes of that smoothing (`twicing_smooth`; 1: plain Laplacian). Must match the
    weights' training (`DataConfig.presmooth_passes`)."""
    presmooth_adaptive: bool = True
    """Choose the pre-smoothing's count per vertex (`adaptive_twicing`, `presmooth_iterations`
    its pilot's count). The shipped weights were fine-tuned on fixed twicing at 30 and are fed
    this."""
    presmooth_learned: bool = True
    """The pre-smoothing is the selector's blend of twicings (`selector_presmoothed`, the
    `selector` weights; its candidates and pilot are fixed by those weights), in place of
    `presmooth_adaptive`'s choice; `presmooth_iterations` 0 still turns pre-smoothing off."""
    bounded_noise: BoundedNoiseConfig = field(default_factory=BoundedNoiseConfig)
    """The pre-smoothing (ldm, regressor, selector) ends by moving each vertex to the middle of
    its neighbourhood's residual range where the noise is bounded (`bounded_noise.py`; rings
    0: off)."""
    correction_gain: float = 0.7
    """Share of the networks' depth correction (enhanced minus base depth) the update
    follows, every vertex alike, when `learned_gain` is off. Chosen on the validation meshes
    (spot, fandisk; not the bunny) under the benchmark's protocol
    (`benchmarks/enhance_gain.py`), for the shipped LDM: C2M RMS at gains 0.1 / 0.2 / 0.35 /
    0.5 / 0.7 / 1.0 was 0.686 / 0.683 / 0.679 / 0.676 / 0.674 / 0.673 mm on spot and 0.723 /
    0.716 / 0.708 / 0.704 / 0.704 / 0.715 on fandisk; 0.7 gives the lowest mean. (0.35 was
    chosen while spot was read split along its texture seams, which the networks handled
    worse.)"""
    learned_gain: bool = True
    """Each vertex follows its own share of the networks' correction, given by the method's
    vertex gain network (`vertex_gain.py`; weights `ldm_gain`, `regressor_gain`) from how its
    views agree; False: every vertex follows `correction_gain`. On the validation meshes
    under the benchmark's protocol the LDM's mean C2M RMS went from 0.7427 mm (the best fixed
    gain) to 0.7314, the bunny's from 0.9190 to 0.9157."""
    min_noise_ratio: float = 0.05
    """The networks (ldm, regressor) leave a mesh unchanged whose estimated noise
    (`noise_to_edge_ratio`) is below this; 0 always enhances. Their pre-smoothing removes
    detail they cannot restore, so below some noise they do harm: on spot and fandisk under
    the benchmark's protocol with the noise amplitude swept (`benchmarks/enhance_gate.py`) the
    LDM's result matched the input's error at ratios 0.057 and 0.048 with the selector's
    pre-smoothing and the vertex gains (0.059 on spot read split along its texture seams;
    0.053 and 0.044 with one fixed gain, 0.072 and 0.064
    with adaptive twicing, 0.11 and 0.14 with ten Laplacian iterations). A reconstruction of
    the synthetic bunny capture measures 0.01 (enhanced without the gate: 0.70 -> 0.86 mm)."""
    self_check: bool = False
    """Before the networks' update (ldm, regressor), check on a simulated copy of the mesh
    whether they beat the same pipeline without them (`self_check.py`): the classical result
    (the base, then the normal filter) with the mesh's own residuals from the base shuffled
    back on, enhanced both ways and scored against it. Where the networks lose there, the
    result is the classical one, light-remeshed. It costs one more pre-smoothing, render,
    network pass and update. Off by default: on a GPU that is most of the time per mesh."""
    update: UpdateConfig = field(default_factory=UpdateConfig)
    """How vertices follow the enhanced depth."""
    normal_filter: NormalFilterConfig = field(default_factory=NormalFilterConfig)
    """The bilateral normal filter that ends the view-based update (`normal_filter.py`;
    `normal_iterations` 0: off)."""
    remesh_iterations: int = 1
    """Rounds of a light isotropic remesh at the mesh's own mean edge length after the
    view-based update (the update itself already puts back moves that turn a face over),
    followed by the remesh stage's angle clean-up; the kernel's result is dropped where it
    adds faces outside the angle criteria (`light_remesh`); 0 keeps the connectivity. On
    the benchmark's bunny it takes the LDM from 0.9206 to 0.9172 mm C2M RMS (0.9192 to 0.9157
    under the protocol before long boundary edges were split, where it took the reverse RMS
    from 1.028 to 1.038 mm; `benchmarks/enhance_remesh.py`). It is 3.9 of the 7.0 s on 2 CPU
    cores and would be nearly all of the time on a GPU."""
    remesh_ahead: bool | None = None
    """Start the light remesh's kernel on the mesh the update moves, beside the networks, and
    carry its result onto the moved mesh (`pipeline.reconstruct.remesh.speculative`), rather
    than remesh the
    moved mesh after the update. None: where the device is an accelerator, whose host has
    cores to spare while the networks and the update run there; on 2 CPU cores the kernel
    only takes them from the networks (the bunny: no faster). The kernel's choices are then
    made on the surface before the update: 0.0-0.21 % more C2M RMS on the benchmark's ten
    meshes (the bunny's LDM 0.66126 -> 0.66218 mm)."""
    device: str = "auto"
    """Torch device for the networks: auto (CUDA when present), cpu or cuda."""
    weights: dict[str, bytes] | None = None
    """safetensors bytes per model ('regressor', 'vae', 'ldm', 'selector', 'ldm_gain',
    'regressor_gain'); None or a model left out: the shipped weights."""


def validate_config(config: EnhanceConfig) -> None:
    """Raises ValueError naming the first field of `config` that is out of range."""
    if config.method not in METHODS:
        raise ValueError(f"method: {config.method!r} is not one of {', '.join(METHODS)}")
    if config.views < 1:
        raise ValueError(f"views must be >= 1, got {config.views}")
    if config.resolution < 16:
        raise ValueError(f"resolution must be >= 16 pixels, got {config.resolution}")
    if config.steps < 1:
        raise ValueError(f"steps must be >= 1, got {config.steps}")
    if not 0.0 < config.strength <= 1.0:
        raise ValueError(f"strength must be in (0, 1], got {config.strength}")
    if config.ensemble not in (1, 2, 4, 8):
        raise ValueError(f"ensemble must be 1, 2, 4 or 8, got {config.ensemble}")
    if config.iterations < 0:
        raise ValueError(f"iterations must be >= 0, got {config.iterations}")
    if not 0.0 < config.correction_gain <= 2.0:
        raise ValueError(f"correction_gain must be in (0, 2], got {config.correction_gain}")
    if config.min_noise_ratio < 0:
        raise ValueError(f"min_noise_ratio must be >= 0, got {config.min_noise_ratio}")
    if config.presmooth_iterations < 0:
        raise ValueError(
            f"presmooth_iterations must be >= 0, got {config.presmooth_iterations}"
        )
    if config.presmooth_passes < 1:
        raise ValueError(f"presmooth_passes must be >= 1, got {config.presmooth_passes}")
    if config.bounded_noise.rings < 0 or config.bounded_noise.smoothing < 0:
        raise ValueError(
            f"bounded_noise: rings and smoothing must be >= 0, got {config.bounded_noise.rings}"
            f" and {config.bounded_noise.smoothing}")
    if config.bounded_noise.weight_passes < 0:
        raise ValueError(
            f"bounded_noise: weight_passes must be >= 0, got {config.bounded_noise.weight_passes}")
    if config.remesh_iterations < 0:
        raise ValueError(f"remesh_iterations must be >= 0, got {config.remesh_iterations}")
