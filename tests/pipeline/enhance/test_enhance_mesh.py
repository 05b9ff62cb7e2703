"""`enhance_mesh` end to end on a noisy sphere: the three methods, the learned vertex gains,
the noise gate, progress, and results that do not depend on the listing or the device."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from pipeline.enhance import EnhanceConfig, enhance_mesh
from pipeline.enhance.update.normal_filter import NormalFilterConfig
from pipeline.geometry.mesh import TriangleMesh

OFF = NormalFilterConfig(normal_iterations=0)
"""The update's own moves, with no normal filter after them."""


def test_the_classical_method_is_the_pre_smoothing_and_the_normal_filter(
        noisy_sphere: tuple[TriangleMesh, TriangleMesh]) -> None:
    """No render, no network: the selector's blend ended by the midrange estimator, then the
    normal filter, in the canonical order (here without the light remesh)."""
    from pipeline.enhance.inference import selector_presmoothed
    from pipeline.enhance.update.normal_filter import normal_filter
    from pipeline.enhance.weights import shipped_bytes
    from pipeline.enhance.weights.loading import load_selector
    from pipeline.geometry.order import reordered, restored, spatial_order

    _, noisy = noisy_sphere
    config = EnhanceConfig(method="classical", remesh_iterations=0, min_noise_ratio=0.0,
                           device="cpu")
    order = spatial_order(noisy)
    base = selector_presmoothed(reordered(noisy, order), load_selector(shipped_bytes("selector")),
                                config.bounded_noise, "cpu")
    expected = restored(normal_filter(base, config.normal_filter, "cpu"), order)
    out = enhance_mesh(noisy, config)
    np.testing.assert_array_equal(out.faces, noisy.faces)
    np.testing.assert_array_equal(out.vertices_m, expected.vertices_m)


@pytest.mark.parametrize("method", ["ldm", "regressor"])
def test_learned_gains_give_each_vertex_its_own_share_of_the_correction(
        noisy_sphere: tuple[TriangleMesh, TriangleMesh], method: str) -> None:
    """With the shipped vertex gains each seen vertex follows its own share of the whole
    correction (gain 1), between none and twice it, and the shares differ between vertices;
    `enhance_mesh` runs these very steps."""
    from pipeline.enhance.enhancement import (
        enhance_renders,
        learned_vertex_gain,
        update_inputs,
    )
    from pipeline.enhance.update.steps import apply_view_steps, view_steps
    from pipeline.geometry.order import reordered, restored, spatial_order

    _, noisy = noisy_sphere
    config = EnhanceConfig(method=method, resolution=96, remesh_iterations=0, min_noise_ratio=0.0,
                           normal_filter=OFF, device="cpu")
    order = spatial_order(noisy)
    ordered = reordered(noisy, order)
    inputs = update_inputs(ordered, config, "cpu")
    enhanced = enhance_renders(inputs.base_renders, inputs.renders, config)
    steps = view_steps(inputs.base, inputs.base_renders, enhanced, inputs.update)
    gain = learned_vertex_gain(ordered, steps, config)
    whole = apply_view_steps(inputs.base, steps, inputs.update)[0]
    learned = apply_view_steps(inputs.base, steps, inputs.update, gain)[0]
    full = whole.vertices_m - inputs.base.vertices_m
    moves = learned.vertices_m - inputs.base.vertices_m
    moved = np.linalg.norm(full, axis=1) > 1e-5
    assert moved.mean() > 0.5
    along = np.sum(moves[moved] * full[moved], axis=1) / np.sum(full[moved] ** 2, axis=1)
    assert np.all(along > -1e-6) and np.all(along < 2.0 + 1e-6)
    assert np.percentile(along, 90) - np.percentile(along, 10) > 0.05
    np.testing.assert_array_equal(enhance_mesh(noisy, config).vertices_m,
                                  restored(learned, order).vertices_m)


@pytest.mark.parametrize("method", ["views", "taubin", "selector", "magic"])
def test_a_method_not_offered_is_named_with_the_three(method: str) -> None:
    from pipeline.enhance.config import validate_config

    with pytest.raises(ValueError, match="one of regressor, ldm, classical") as raised:
        validate_config(EnhanceConfig(method=method))
    assert ("'classical' replaces the smoothers" in str(raised.value)) == (method != "magic")


@pytest.mark.parametrize("method", ["ldm", "classical"])
def test_a_mesh_with_coordinates_not_finite_is_named(method: str) -> None:
    from dataclasses import replace

    from tests.pipeline.meshes import sphere

    mesh = sphere()
    vertices_m = mesh.vertices_m.copy()
    vertices_m[3, 0], vertices_m[7, 2] = np.nan, np.inf
    with pytest.raises(ValueError, match="mesh: 2 vertices have a coordinate that is not finite"):
        enhance_mesh(replace(mesh, vertices_m=vertices_m), EnhanceConfig(method=method))


def test_the_networks_leave_a_clean_mesh_and_enhance_a_noisy_one() -> None:
    from pipeline.enhance.noise_level import noise_to_edge_ratio
    from pipeline.enhance.training.data import noisy_along_normals
    from pipeline.geometry.mesh import mean_edge_length_m
    from tests.pipeline.meshes import sphere

    clean = sphere(0.5, 40)
    noisy = noisy_along_normals(clean, mean_edge_length_m(clean), np.random.default_rng(0))
    config = EnhanceConfig(method="regressor", resolution=64, remesh_iterations=0)
    assert noise_to_edge_ratio(clean) < config.min_noise_ratio < noise_to_edge_ratio(noisy)
    assert enhance_mesh(clean, config) is clean
    assert not np.allclose(enhance_mesh(noisy, config).vertices_m, noisy.vertices_m)
    # 0 turns the gate off: the clean mesh is pre-smoothed and corrected like any other.
    forced = enhance_mesh(clean, EnhanceConfig(method="regressor", resolution=64,
                                               remesh_iterations=0, min_noise_ratio=0.0))
    assert not np.allclose(forced.vertices_m, clean.vertices_m)


def test_a_negative_noise_gate_is_named() -> None:
    from pipeline.enhance.config import validate_config

    with pytest.raises(ValueError, match="min_noise_ratio"):
        validate_config(EnhanceConfig(min_noise_ratio=-0.1))


@pytest.mark.parametrize("method", ["regressor", "classical"])
def test_progress_names_every_stage_in_order_and_ends_at_one(method: str) -> None:
    from pipeline.enhance.enhancement import CLASSICAL_STAGE_PROGRESS, STAGE_PROGRESS
    from pipeline.enhance.training.data import noisy_along_normals
    from tests.pipeline.meshes import sphere

    noisy = noisy_along_normals(sphere(0.5, 24), 0.01, np.random.default_rng(0))
    reported: list[float] = []
    enhance_mesh(noisy, EnhanceConfig(method=method, resolution=32, min_noise_ratio=0.0),
                 reported.append)
    shares = STAGE_PROGRESS if method == "regressor" else CLASSICAL_STAGE_PROGRESS
    assert reported == list(shares.values())
    assert reported == sorted(reported) and reported[-1] == 1.0


def test_the_view_update_ends_with_the_normal_filter() -> None:
    """The output is the normal filter's of what the update gives without it (in the stages'
    own order, so to rounding). That the filter helps is its own tests' and the benchmark's
    (`ldm_4_steps_no_normal_filter`): on this sphere the update leaves it little to take."""
    from pipeline.enhance.training.data import noisy_along_normals
    from pipeline.enhance.update.normal_filter import normal_filter
    from tests.pipeline.meshes import sphere

    # Edges short against the radius, as the filter assumes (2.5 cm on a 0.5 m sphere).
    noisy = noisy_along_normals(sphere(0.5, 64), 0.01, np.random.default_rng(0))

    def enhanced(config: NormalFilterConfig) -> TriangleMesh:
        return enhance_mesh(noisy, EnhanceConfig(method="regressor", resolution=96,
                                                 remesh_iterations=0, min_noise_ratio=0.0,
                                                 normal_filter=config))

    filtered, unfiltered = enhanced(NormalFilterConfig()), enhanced(OFF)
    assert not np.allclose(filtered.vertices_m, unfiltered.vertices_m, atol=1e-6)
    np.testing.assert_allclose(filtered.vertices_m,
                               normal_filter(unfiltered, NormalFilterConfig()).vertices_m,
                               atol=1e-9)
    np.testing.assert_array_equal(filtered.faces, unfiltered.faces)


@pytest.mark.parametrize(("method", "remesh_iterations"),
                         [("regressor", 0), ("classical", 0), ("regressor", 2)])
def test_the_result_depends_on_the_surface_not_on_how_it_is_listed(
        method: str, remesh_iterations: int) -> None:
    from pipeline.enhance.training.data import noisy_along_normals
    from pipeline.geometry.order import MeshOrder, reordered
    from tests.pipeline.meshes import sphere

    # The stages run in a canonical order of their own (`mesh_order`) and hand back the
    # input's where they keep the faces: so a mesh listed otherwise (vertices, faces, and
    # the corner each face starts at) gives the same result bit for bit, listed alike.
    noisy = noisy_along_normals(sphere(0.5, 48), 0.01, np.random.default_rng(0))
    rng = np.random.default_rng(1)
    listing = MeshOrder(vertex_order=rng.permutation(noisy.vertex_count),
                        face_order=rng.permutation(noisy.face_count),
                        face_start=rng.integers(0, 3, noisy.face_count))
    config = EnhanceConfig(method=method, resolution=64, remesh_iterations=remesh_iterations,
                           min_noise_ratio=0.0)
    out = enhance_mesh(noisy, config)
    listed_out = enhance_mesh(reordered(noisy, listing), config)
    expected = reordered(out, listing) if remesh_iterations == 0 else out
    assert np.array_equal(listed_out.faces, expected.faces)
    assert np.array_equal(listed_out.vertices_m, expected.vertices_m)
    assert not np.allclose(out.vertices_m[:10], noisy.vertices_m[:10])


def test_the_accelerator_path_gives_the_cpu_paths_mesh(
        noisy_sphere: tuple[TriangleMesh, TriangleMesh], monkeypatch: pytest.MonkeyPatch) -> None:
    """On a GPU the geometry stages run in torch there (render, noise gate, selector's
    features, bounded-noise refinement, view update, normal filter): forced onto the CPU
    here, they give the numpy and scipy path's mesh, to rounding."""
    import pipeline.enhance.device as device

    _, noisy = noisy_sphere
    config = EnhanceConfig(method="ldm", resolution=96, device="cpu", remesh_iterations=0)
    host = enhance_mesh(noisy, config)
    monkeypatch.setattr(device, "accelerator", lambda name: name)
    there = enhance_mesh(noisy, config)
    assert not np.allclose(host.vertices_m, noisy.vertices_m, atol=1e-4)
    np.testing.assert_array_equal(there.faces, host.faces)
    # The rasterizer and open3d's float32 ray cast differ by ~1e-7 of the depth range.
    np.testing.assert_allclose(there.vertices_m, host.vertices_m, rtol=0, atol=1e-7)


def test_the_accelerator_path_remeshed_ahead_gives_the_cpu_paths_mesh(
        noisy_sphere: tuple[TriangleMesh, TriangleMesh], monkeypatch: pytest.MonkeyPatch) -> None:
    """With the light remesh started ahead (the default on a GPU), the accelerator path also
    carries the kernel's result onto the moved mesh and measures its angles there
    (`transfer_torch`): forced onto the CPU, the same faces and vertices as the host's."""
    import pipeline.enhance.device as device

    _, noisy = noisy_sphere
    config = EnhanceConfig(method="ldm", resolution=96, device="cpu", remesh_ahead=True)
    host = enhance_mesh(noisy, config)
    monkeypatch.setattr(device, "accelerator", lambda name: name)
    there = enhance_mesh(noisy, config)
    assert host.face_count != noisy.face_count  # remeshed
    np.testing.assert_array_equal(there.faces, host.faces)
    np.testing.assert_allclose(there.vertices_m, host.vertices_m, rtol=0, atol=1e-7)


@pytest.mark.skipif(not __import__("torch").cuda.is_available(), reason="no CUDA device")
def test_the_cuda_path_gives_the_cpu_paths_mesh(
        noisy_sphere: tuple[TriangleMesh, TriangleMesh]) -> None:
    """The GPU's float32 renders and network kernels give the CPU's faces and its vertices to
    microns."""
    _, noisy = noisy_sphere
    config = EnhanceConfig(method="ldm", resolution=96, remesh_iterations=0)
    host = enhance_mesh(noisy, replace(config, device="cpu"))
    gpu = enhance_mesh(noisy, replace(config, device="cuda"))
    np.testing.assert_array_equal(gpu.faces, host.faces)
    # float32 renders and the networks' kernels on the GPU: microns, not rounding.
    np.testing.assert_allclose(gpu.vertices_m, host.vertices_m, rtol=0, atol=1e-5)


@pytest.mark.skipif(not __import__("torch").cuda.is_available(), reason="no CUDA device")
def test_the_cuda_path_gives_one_mesh_whatever_the_run_or_the_listing(
        noisy_sphere: tuple[TriangleMesh, TriangleMesh]) -> None:
    """On the CPU `test_the_result_depends_on_the_surface_not_on_how_it_is_listed` holds it bit
    for bit. On a GPU a process's calls after its first agree with each other whatever the
    listing, to the last bits of the atomic adds, with the same faces; the first call in a
    process has the same faces and its vertices within microns: its pre-smoothing (the
    selector's, in torch) differs from later ones' in the last bits, which the depth
    networks' TF32 convolutions carry on. So a worker gives one mesh for one input from its
    second job on, and the first job's differs by far less than the result's error."""
    from pipeline.geometry.order import MeshOrder, reordered

    _, noisy = noisy_sphere
    rng = np.random.default_rng(1)
    listing = MeshOrder(vertex_order=rng.permutation(noisy.vertex_count),
                        face_order=rng.permutation(noisy.face_count),
                        face_start=rng.integers(0, 3, noisy.face_count))
    config = EnhanceConfig(method="ldm", resolution=96, device="cuda", min_noise_ratio=0.0)
    first, second, third = (enhance_mesh(noisy, config) for _ in range(3))
    listed = enhance_mesh(reordered(noisy, listing), config)
    for other in (first, third, listed):
        np.testing.assert_array_equal(other.faces, second.faces)
    for other in (third, listed):
        np.testing.assert_allclose(other.vertices_m, second.vertices_m, rtol=0, atol=1e-12)
    np.testing.assert_allclose(first.vertices_m, second.vertices_m, rtol=0, atol=5e-6)
