"""The networks one enhancement runs, loaded once and kept for many meshes.

`enhance_mesh` loads what its method needs (the selector of the pre-smoothing; for ldm and
regressor also the depth network and its vertex gain network) on every call when it is given
none. Loading builds modules and places their weights, mostly in the interpreter, so a worker
keeps one `EnhanceNetworks` between the meshes it enhances.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from pipeline.enhance.config import NETWORK_METHODS

if TYPE_CHECKING:
    from pipeline.enhance.config import EnhanceConfig

__all__ = ["NETWORK_METHODS", "EnhanceNetworks", "load_networks", "networks_key",
           "selector_for", "uses_gain"]


@dataclass(frozen=True)
class EnhanceNetworks:
    """The loaded networks of one method, device and set of weights (`load_networks`)."""

    key: tuple[Any, ...]
    """What they were loaded for (`networks_key`)."""
    enhancer: Any | None
    """The depth network on its device (`loading.load_enhancer`): `LDMModels` or a
    regressor; None for the classical method."""
    selector: Any
    """The pre-smoothing's selector (`loading.load_selector`)."""
    gain: Any | None
    """The vertex gain network (`loading.load_vertex_gain`); None for the classical method."""

    def fits(self, config: EnhanceConfig) -> bool:
        """Whether these are the networks `config` would load."""
        return self.key == networks_key(config)


def uses_gain(config: EnhanceConfig) -> bool:
    """Whether `config`'s enhancement runs a vertex gain network (the depth networks' update)."""
    return config.method in NETWORK_METHODS


def networks_key(config: EnhanceConfig) -> tuple[Any, ...]:
    """What decides which networks `config` loads, and where: its method, its device and the
    weights it names."""
    from pipeline.enhance.device import resolve_device

    weights = tuple(sorted((config.weights or {}).items()))
    return (config.method, resolve_device(config.device).type, weights)


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
    selector = load_selector(model_bytes(config, "selector"))
    gain = (load_vertex_gain(model_bytes(config, f"{config.method}_gain"))
            if uses_gain(config) else None)
    return EnhanceNetworks(networks_key(config), enhancer, selector, gain)
