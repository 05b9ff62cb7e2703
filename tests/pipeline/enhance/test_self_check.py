"""The self-check: a simulated copy of the mesh, as noisy as it, decides whether the
networks' update is kept."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.enhance import EnhanceConfig, enhance_mesh
from pipeline.enhance.enhancement import CHECKED_STAGE_PROGRESS
from pipeline.enhance.self_check import (
    SelfCheck,
    residuals_m,
    scored,
    simulated_copy,
)
from pipeline.geometry.mesh import TriangleMesh, vertex_normals
from tests.pipeline.meshes import sphere

SPHERE = sphere(resolution=12)


def _moved_along_normals(mesh: TriangleMesh, offsets_m: np.ndarray) -> TriangleMesh:
    normals = vertex_normals(mesh.vertices_m, mesh.faces).astype(np.float64)
    return mesh.with_vertices(mesh.vertices_m + normals * offsets_m[:, None])


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**32 - 1), st.floats(1e-4, 0.05))
def test_the_residuals_are_the_offsets_along_the_bases_normals(seed: int, amplitude_m: float
                                                              ) -> None:
    offsets_m = np.random.default_rng(seed).uniform(-amplitude_m, amplitude_m,
                                                    SPHERE.vertex_count)
    noisy = _moved_along_normals(SPHERE, offsets_m)
    assert np.allclose(residuals_m(noisy, SPHERE), offsets_m, atol=1e-7)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(0, 2**32 - 1))
def test_the_copy_carries_the_same_residuals_shuffled(noise_seed: int, seed: int) -> None:
    """The copy's noise has the input's distribution exactly (the same values), on the
    truth's surface, and the seed alone decides where each value goes."""
    offsets_m = np.random.default_rng(noise_seed).uniform(-0.01, 0.01, SPHERE.vertex_count)
    noisy = _moved_along_normals(SPHERE, offsets_m)
    truth = SPHERE.with_vertices(SPHERE.vertices_m * 1.1)
    copy = simulated_copy(noisy, SPHERE, truth, seed)
    assert np.array_equal(copy.faces, truth.faces)
    copied_m = residuals_m(copy, truth)
    assert np.allclose(np.sort(copied_m), np.sort(offsets_m), atol=1e-7)
    assert not np.allclose(copied_m, offsets_m)
    assert np.array_equal(simulated_copy(noisy, SPHERE, truth, seed).vertices_m, copy.vertices_m)
    other = simulated_copy(noisy, SPHERE, truth, seed + 1)
    assert not np.array_equal(other.vertices_m, copy.vertices_m)


def test_the_nearer_result_wins() -> None:
    noisy = _moved_along_normals(SPHERE, np.full(SPHERE.vertex_count, 0.002))
    nearer = _moved_along_normals(SPHERE, np.full(SPHERE.vertex_count, 0.001))
    check = scored(noisy, nearer, SPHERE)
    assert check.networks_help
    assert check.with_networks_rms_m < check.without_networks_rms_m
    assert scored(nearer, noisy, SPHERE).networks_help is False
    assert SelfCheck(1e-3, 1e-3).networks_help is False  # a tie keeps the classical result
    assert scored(SPHERE, SPHERE, SPHERE).with_networks_rms_m < 1e-7  # float32 ray casting


def _harmful_regressor() -> bytes:
    """The shipped regressor with its corrections turned round and tripled: a network that
    makes every mesh worse."""
    import torch

    from pipeline.enhance.weights import shipped_bytes
    from pipeline.enhance.weights.loading import load_regressor, regressor_to_bytes

    model = load_regressor(shipped_bytes("regressor"))
    with torch.no_grad():
        for name, p in model.named_parameters():
            if "conv_out" in name:
                p.mul_(-3.0)
    return regressor_to_bytes(model)


@pytest.mark.parametrize("harmful", [True, False], ids=["harmful", "shipped"])
def test_the_self_check_keeps_the_networks_update_only_where_it_wins_on_the_copy(
        noisy_sphere: tuple[TriangleMesh, TriangleMesh], harmful: bool) -> None:
    """A regressor that harms is caught and the classical result comes back; the mesh is
    always the result of the branch the check chose."""
    clean, noisy = noisy_sphere
    config = EnhanceConfig(method="regressor", resolution=96, remesh_iterations=0,
                           min_noise_ratio=0.0,
                           weights={"regressor": _harmful_regressor()} if harmful else None)
    checks: list[SelfCheck] = []
    reported: list[float] = []
    result = enhance_mesh(noisy, replace(config, self_check=True), reported.append,
                          on_check=checks.append)
    assert len(checks) == 1
    # Live progress through the check, in order, to the end whichever result is kept.
    stages = ["render", "presmooth", "check"] + (
        ["network", "update", "remesh"] if checks[0].networks_help else ["remesh"])
    assert reported == [CHECKED_STAGE_PROGRESS[s] for s in stages]
    check = checks[0]
    assert 0 < check.without_networks_rms_m < 0.01 and 0 < check.with_networks_rms_m < 0.05
    unchecked = enhance_mesh(noisy, config)
    classical = enhance_mesh(noisy, replace(config, method="classical"))
    chosen = unchecked if check.networks_help else classical
    np.testing.assert_array_equal(result.vertices_m, chosen.vertices_m)
    if harmful:
        assert not check.networks_help
        # It was right to: the harmful update is further from the truth.
        assert not scored(classical, unchecked, clean).networks_help


def test_without_the_self_check_nothing_is_told(
        noisy_sphere: tuple[TriangleMesh, TriangleMesh]) -> None:
    _, noisy = noisy_sphere
    checks: list[SelfCheck] = []
    enhance_mesh(noisy, EnhanceConfig(method="regressor", resolution=32, remesh_iterations=0,
                                      min_noise_ratio=0.0), on_check=checks.append)
    enhance_mesh(noisy, EnhanceConfig(method="classical", self_check=True,
                                      min_noise_ratio=0.0), on_check=checks.append)
    assert checks == []


@pytest.mark.parametrize("harmful", [True, False], ids=["harmful", "shipped"])
def test_the_accelerator_path_checks_as_the_cpu_path_does(
        noisy_sphere: tuple[TriangleMesh, TriangleMesh], monkeypatch: pytest.MonkeyPatch,
        harmful: bool) -> None:
    """On a GPU the check's stages run in torch there and the light remesh starts ahead (the
    default there): forced onto the CPU, the same decision and the host path's mesh. (On this
    sphere the shipped networks and the classical method are within 1 % of each other.)"""
    import pipeline.enhance.device as device

    _, noisy = noisy_sphere
    config = EnhanceConfig(method="regressor", resolution=96, device="cpu", remesh_ahead=True,
                           min_noise_ratio=0.0, self_check=True,
                           weights={"regressor": _harmful_regressor()} if harmful else None)
    host_checks: list[SelfCheck] = []
    host = enhance_mesh(noisy, config, on_check=host_checks.append)
    monkeypatch.setattr(device, "accelerator", lambda name: name)
    there_checks: list[SelfCheck] = []
    there = enhance_mesh(noisy, config, on_check=there_checks.append)
    assert there_checks[0].networks_help == host_checks[0].networks_help
    assert not (harmful and host_checks[0].networks_help)
    assert there_checks[0].with_networks_rms_m == pytest.approx(
        host_checks[0].with_networks_rms_m, rel=1e-4)
    assert host.face_count != noisy.face_count  # remeshed either way
    np.testing.assert_array_equal(there.faces, host.faces)
    np.testing.assert_allclose(there.vertices_m, host.vertices_m, rtol=0, atol=1e-7)


@pytest.mark.skipif(not __import__("torch").cuda.is_available(), reason="no CUDA device")
def test_the_cuda_path_checks_as_the_cpu_path_does(
        noisy_sphere: tuple[TriangleMesh, TriangleMesh]) -> None:
    """The harmful regressor: a margin no float32 kernel can turn round."""
    _, noisy = noisy_sphere
    config = EnhanceConfig(method="regressor", resolution=96, remesh_iterations=0,
                           min_noise_ratio=0.0, self_check=True,
                           weights={"regressor": _harmful_regressor()})
    results, checks = [], []
    for name in ("cpu", "cuda"):
        results.append(enhance_mesh(noisy, replace(config, device=name),
                                    on_check=checks.append))
    assert not checks[0].networks_help and not checks[1].networks_help
    np.testing.assert_allclose(results[1].vertices_m, results[0].vertices_m, rtol=0, atol=1e-5)
