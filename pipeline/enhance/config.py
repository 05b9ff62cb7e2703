"""`EnhanceConfig`: how `enhancement.enhance_mesh` enhances a mesh, and its checks."""

from __future__ import annotations

from dataclasses import dataclass, field

from pipeline.enhance.presmooth.midrange import BoundedNoiseConfig
from pipeline.enhance.update.normal_filter import NormalFilterConfig
from pipeline.enhance.update.steps import UpdateConfig

NETWORK_METHODS = ("regressor", "ldm")
"""The methods whose depth correction is a network."""
METHODS = (*NETWORK_METHODS, "classical")
"""Every method `enhance_mesh` runs."""
REPLACED_BY_CLASSICAL = ("taubin", "laplacian", "twicing", "adaptive", "bilateral", "selector",
                         "views")
"""Method names refused with a pointer to `classical`, the best enhancement without a depth
network: the classical smoothers, the selector alone and the network-free view update."""

_PRESMOOTHING = ("the pre-smoothing is always the selector's blend of twicings (scale selection) "
                 "ended by the midrange estimator")
_GAIN = "the per-vertex gain network sets each vertex's share of the correction"
REMOVED_SETTINGS = {
    "ensemble": "each view is corrected once",
    "iterations": "method 'classical' replaces the smoothers it counted",
    "presmooth_iterations": _PRESMOOTHING,
    "presmooth_passes": _PRESMOOTHING,
    "presmooth_adaptive": _PRESMOOTHING,
    "presmooth_learned": _PRESMOOTHING,
    "correction_gain": _GAIN,
    "learned_gain": _GAIN,
}
"""Job settings of the enhancement that no longer exist, each with what takes its place: a job
that sets one is refused with that line rather than told the setting is unknown."""


@dataclass(frozen=True)
class EnhanceConfig:
    """How to enhance a mesh."""

    method: str = "regressor"
    """regressor or ldm: the network corrects the pre-smoothed mesh's depth views and the
    vertices follow; classical: the same pre-smoothing and ending with no network between.
    The regressor is the default: the LDM's diffusion steps add nothing over it
    (docs/decisions/regressor-default.md)."""
    views: int = 6
    """Number of depth views the networks correct (the six axis views first)."""
    resolution: int = 256
    """Depth image side in pixels."""
    steps: int = 4
    """DDIM steps of the LDM (1: one-step mode)."""
    strength: float = 0.5
    """How far into the noise schedule the LDM's sampling starts from the base latent (0, 1]."""
    seed: int = 0
    """Seed of the LDM's start noise and of the self-check's shuffle."""
    bounded_noise: BoundedNoiseConfig = field(default_factory=BoundedNoiseConfig)
    """The midrange estimator that ends the pre-smoothing where the noise is bounded
    (`presmooth/midrange.py`; rings 0: off)."""
    min_noise_ratio: float = 0.05
    """A mesh whose estimated noise (`noise_to_edge_ratio`) is below this is returned as it
    came: the pre-smoothing would remove detail that nothing restores. 0 always enhances."""
    self_check: bool = False
    """Before the networks' update, check on a simulated copy of the mesh whether they beat
    the classical method (`self_check.py`) and return the classical result where they lose.
    Off by default: it costs one more pre-smoothing, render, network pass and update."""
    update: UpdateConfig = field(default_factory=UpdateConfig)
    """How vertices follow the corrected depth."""
    normal_filter: NormalFilterConfig = field(default_factory=NormalFilterConfig)
    """The bilateral normal filter that ends the update (`normal_iterations` 0: off)."""
    remesh_iterations: int = 1
    """Rounds of the light remesh that cleans the result up (`clean/light_remesh.py`); 0 keeps
    the input's connectivity."""
    remesh_ahead: bool | None = None
    """Start the light remesh's kernel on the mesh the update moves, beside the networks, and
    carry its result onto the moved mesh (speculative remesh), rather than remesh the moved
    mesh after the update. None: where the device is an accelerator, whose host has cores to
    spare while the networks run there."""
    device: str = "auto"
    """Torch device for the networks: auto (CUDA when present), cpu or cuda."""
    weights: dict[str, bytes] | None = None
    """safetensors bytes per model ('regressor', 'vae', 'ldm', 'selector', 'ldm_gain',
    'regressor_gain'); None or a model left out: the shipped weights."""


def check_method(method: str) -> None:
    """Raises ValueError naming the methods when `method` is not one of them."""
    if method in METHODS:
        return
    offered = ", ".join(METHODS)
    if method in REPLACED_BY_CLASSICAL:
        raise ValueError(f"method: {method!r} is no longer offered; 'classical' replaces the "
                         f"smoothers (one of {offered})")
    raise ValueError(f"method: {method!r} is not one of {offered}")


def validate_config(config: EnhanceConfig) -> None:
    """Raises ValueError naming the first field of `config` that is out of range."""
    check_method(config.method)
    if config.views < 1:
        raise ValueError(f"views must be >= 1, got {config.views}")
    if config.resolution < 16:
        raise ValueError(f"resolution must be >= 16 pixels, got {config.resolution}")
    if config.steps < 1:
        raise ValueError(f"steps must be >= 1, got {config.steps}")
    if not 0.0 < config.strength <= 1.0:
        raise ValueError(f"strength must be in (0, 1], got {config.strength}")
    if config.min_noise_ratio < 0:
        raise ValueError(f"min_noise_ratio must be >= 0, got {config.min_noise_ratio}")
    if config.bounded_noise.rings < 0 or config.bounded_noise.smoothing < 0:
        raise ValueError(
            f"bounded_noise: rings and smoothing must be >= 0, got {config.bounded_noise.rings}"
            f" and {config.bounded_noise.smoothing}")
    if config.remesh_iterations < 0:
        raise ValueError(f"remesh_iterations must be >= 0, got {config.remesh_iterations}")
