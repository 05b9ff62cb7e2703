"""The networks one enhancement runs, loaded once and kept for many meshes.

`enhance_mesh` loads what its method needs (the LDM or the regressor, the selector of the
pre-smoothing, the vertex gain network) on every call when it is given none. Loading the LDM
builds its modules and places their weights: 0.10-0.15 s on 2 CPU cores, of a mesh's 4 s, and
most of it is the interpreter's, so a GPU's host pays it too. A worker keeps one
`EnhanceNetworks` between the meshes it enhances (`workers.runner.WorkerContext`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from pipeline.enhance.config import EnhanceConfig

NETWORK_METHODS = ("ldm", "regressor")
"""The methods whose depth enhancement is a network."""


@dataclass(frozen=True)
class EnhanceNetworks:
    """The loaded networks of one method, device and set of weights (`load_networks`)."""

    key: tuple[Any, ...]
    """What they were loaded for (`networks_key`)."""
    enhancer: Any | None
    """The depth network on its device (`loading.load_enhancer`): `LDMModels` or a
    regressor; None for the methods without one."""
    selector: Any | None
    """The pre-smoothing's selector (`loading.load_selector`), where the method uses one."""
    gain: Any | None
    """The vertex gain network (`loading.load_vertex_gain`), where the method uses one."""

    def fits(self, config: EnhanceConfig) -> bool:
        """Whether these are the networks `config` would load."""
        return self.key == networks_key(config)


def uses_selector(config: EnhanceConfig) -> bool:
    """Whether `config`'s enhancement runs the selector: as its method, or as the networks'
    pre-smoothing."""
    return config.method == "selector" or (
        config.method in NETWORK_METHODS and config.presmooth_iterations > 0
        and config.presmooth_learned)


def uses_networks(config: EnhanceConfig) -> bool:
    """Whether `config`'s enhancement runs any network (the smoothers run none)."""
    return config.method in NETWORK_METHODS or uses_selector(config)


def uses_gain(config: EnhanceConfig) -> bool:
    """Whether `config`'s enhancement runs a vertex gain network."""
    return config.method in NETWORK_METHODS and config.learned_gain


def networks_key(config: EnhanceConfig) -> tuple[Any, ...]:
    """What decides which networks `config` loads, and where: its method, its device, the
    weights it names and which of the selector and the gain network it uses."""
    from pipeline.enhance.device import resolve_device

    weights = tuple(sorted((config.weights or {}).items()))
    return (config.method, resolve_device(config.device).type, weights,
            uses_selector(config), uses_gain(config))


def selector_for(config: EnhanceConfig, networks: EnhanceNetworks | None):
    """The selector `config` runs: the kept one of `networks`, else loaded now."""
    from pipeline.enhance.weights.loading import load_selector, model_bytes

    if networks is not None:
        return networks.selector
    return load_selector(model_bytes(config, "selector"))


def load_networks(config: EnhanceConfig) -> EnhanceNetworks:
    """The networks `config`'s enhancement runs, loaded onto its device."""
    from pipeline.enhance.weights.loading import (
        load_enhancer,
        load_selector,
        load_vertex_gain,
        model_bytes,
    )

    enhancer = load_enhancer(config) if config.method in NETWORK_METHODS else None
    selector = load_selector(model_bytes(config, "selector")) if uses_selector(config) else None
    gain = (load_vertex_gain(model_bytes(config, f"{config.method}_gain"))
            if uses_gain(config) else None)
    return EnhanceNetworks(networks_key(config), enhancer, selector, gain)
