"""Networks loaded once and kept give what loading them in the call gives."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from pipeline.enhance.config import EnhanceConfig
from pipeline.enhance.enhancement import enhance_mesh
from pipeline.enhance.networks import load_networks, networks_key, uses_gain
from pipeline.enhance.weights import shipped_bytes
from pipeline.geometry.mesh import TriangleMesh

SMALL = EnhanceConfig(resolution=48, remesh_iterations=0, min_noise_ratio=0.0, device="cpu")


@pytest.mark.parametrize("method", ["ldm", "regressor", "classical"])
def test_kept_networks_give_the_loaded_networks_mesh(
        noisy_sphere: tuple[TriangleMesh, TriangleMesh], method: str) -> None:
    """The same mesh bit for bit, for each of two meshes the networks are kept over, and for
    another sampling setting of the LDM (its steps are the config's, not the networks')."""
    _, noisy = noisy_sphere
    config = replace(SMALL, method=method)
    networks = load_networks(config)
    for mesh in (noisy, noisy.with_vertices(noisy.vertices_m * 1.1)):
        kept = enhance_mesh(mesh, config, networks=networks)
        assert np.array_equal(kept.vertices_m, enhance_mesh(mesh, config).vertices_m)
    one_step = replace(config, steps=1)
    assert np.array_equal(enhance_mesh(noisy, one_step, networks=networks).vertices_m,
                          enhance_mesh(noisy, one_step).vertices_m)


def test_networks_for_another_config_are_refused(
        noisy_sphere: tuple[TriangleMesh, TriangleMesh]) -> None:
    _, noisy = noisy_sphere
    networks = load_networks(SMALL)
    for other in (replace(SMALL, method="ldm"), replace(SMALL, method="classical"),
                  replace(SMALL, weights={"regressor_gain": shipped_bytes("ldm_gain")})):
        assert not networks.fits(other)
        with pytest.raises(ValueError, match="networks: loaded for another"):
            enhance_mesh(noisy, other, networks=networks)
    assert networks.fits(replace(SMALL, steps=1, resolution=32, weights={}))


def test_what_each_method_loads() -> None:
    default = load_networks(SMALL)
    assert default.enhancer is not None and default.selector is not None
    assert default.gain is not None
    classical = replace(SMALL, method="classical")
    assert not uses_gain(classical)
    plain = load_networks(classical)
    assert plain.enhancer is None and plain.selector is not None and plain.gain is None
    assert networks_key(SMALL) != networks_key(replace(SMALL, method="ldm"))


def test_the_kept_networks_are_the_ones_run(
        noisy_sphere: tuple[TriangleMesh, TriangleMesh]) -> None:
    """Kept networks whose weights were changed after loading give another mesh: the call
    runs them, not networks of its own."""
    import torch

    _, noisy = noisy_sphere
    config = replace(SMALL, method="regressor")
    networks = load_networks(config)
    loaded = enhance_mesh(noisy, config).vertices_m
    with torch.no_grad():
        for parameter in networks.enhancer.parameters():
            parameter.mul_(1.5)
    assert not np.allclose(enhance_mesh(noisy, config, networks=networks).vertices_m, loaded)
