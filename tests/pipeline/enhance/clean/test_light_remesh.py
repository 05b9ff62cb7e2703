"""The light remesh that ends every enhancement: judged, snapped, and started ahead."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from pipeline.enhance import EnhanceConfig, enhance_mesh
from pipeline.geometry.mesh import TriangleMesh
from pipeline.geometry.repair import triangle_angles_deg
from tests.pipeline.meshes import radial_rms_m


def _sliver_share(mesh: TriangleMesh) -> float:
    return float(np.mean(triangle_angles_deg(mesh.vertices_m, mesh.faces).min(axis=1) < 20))


@pytest.mark.parametrize("method", ["classical", "regressor"])
def test_every_method_ends_with_a_light_remesh(
        noisy_sphere: tuple[TriangleMesh, TriangleMesh], method: str) -> None:
    _, noisy = noisy_sphere
    config = EnhanceConfig(method=method, resolution=96, min_noise_ratio=0.0)
    kept = enhance_mesh(noisy, replace(config, remesh_iterations=0))
    remeshed = enhance_mesh(noisy, config)
    assert kept.face_count == noisy.face_count  # 0: the connectivity is kept
    assert remeshed.face_count != noisy.face_count
    assert _sliver_share(remeshed) < _sliver_share(kept)
    # Projected back onto the enhanced surface: no further from the sphere than before.
    assert radial_rms_m(remeshed) < radial_rms_m(kept) * 1.1


def _outside_share(mesh: TriangleMesh) -> float:
    """Share of faces outside the remesh stage's angle criteria."""
    from pipeline.reconstruct.remesh.isotropic import RemeshConfig, angle_stats

    angles = angle_stats(mesh.vertices_m, mesh.faces, RemeshConfig())
    return angles["share_below_min"] + angles["share_above_max"]


@pytest.mark.parametrize("shape", ["jittered sphere", "long cylinder"])
def test_the_light_remesh_drops_the_kernel_where_it_adds_bad_faces(shape: str) -> None:
    """The isotropic kernel mends the jittered sphere's angles; on the cylinder (2 m sides,
    every face a sliver) one round of it leaves more bad faces than it was given, far past
    the tolerance, and the clean-up alone goes on."""
    import trimesh

    from pipeline.enhance.clean.light_remesh import (
        LIGHT_REMESH_MAX_ADDED_OUTSIDE,
        light_remesh,
        on_light_remesh_grid,
    )
    from pipeline.geometry.mesh import mean_edge_length_m
    from pipeline.reconstruct.remesh.isotropic import RemeshConfig, remesh

    if shape == "jittered sphere":
        s = trimesh.creation.icosphere(4)
        v = s.vertices + np.random.default_rng(0).normal(scale=0.02, size=s.vertices.shape)
    else:
        s = trimesh.creation.cylinder(0.1, 2.0, sections=64)
        v = s.vertices
    mesh = on_light_remesh_grid(TriangleMesh(np.asarray(v, np.float64),
                                             np.asarray(s.faces, np.int32)))
    config = RemeshConfig(target_edge_length_m=mean_edge_length_m(mesh), iterations=1,
                          min_component_share=0.0)
    added = (_outside_share(remesh(mesh, replace(config, cleanup_passes=0))[0])
             - _outside_share(mesh))
    if shape == "jittered sphere":
        assert added < 0
    else:
        assert added > 100 * LIGHT_REMESH_MAX_ADDED_OUTSIDE
    expected = remesh(mesh, config if added < 0 else replace(config, iterations=0))[0]
    out = light_remesh(mesh, 1)
    assert out.face_count == expected.face_count
    np.testing.assert_allclose(out.vertices_m, expected.vertices_m)


@pytest.mark.parametrize("seed", [0, 1])
def test_the_light_remesh_gives_one_mesh_whatever_the_rounding(seed: int) -> None:
    """The tests' sphere has edges of equal length, where the kernel's choices hang on the
    last bits: moved by about 1e-15 m (a GPU's float64 sums against the host's), it must
    still give the same mesh."""
    from pipeline.enhance.clean.light_remesh import light_remesh
    from tests.pipeline.meshes import sphere

    mesh = sphere()
    moved = replace(mesh, vertices_m=mesh.vertices_m + 1e-15 * np.random.default_rng(seed)
                    .normal(size=mesh.vertices_m.shape))
    a, b = light_remesh(mesh, 2), light_remesh(moved, 2)
    assert a.face_count != mesh.face_count  # the kernel ran
    assert np.array_equal(a.faces, b.faces)
    assert np.array_equal(a.vertices_m, b.vertices_m)




def test_the_light_remesh_started_ahead_gives_about_the_same_mesh(
        noisy_sphere: tuple[TriangleMesh, TriangleMesh]) -> None:
    """Started on the base beside the networks and carried onto the moved base (the default
    on a GPU), the light remesh gives about the remesh after the update: as many faces,
    and the same distance from the sphere."""
    _, noisy = noisy_sphere
    config = EnhanceConfig(method="ldm", resolution=96, device="cpu")
    after = enhance_mesh(noisy, replace(config, remesh_ahead=False))
    ahead = enhance_mesh(noisy, replace(config, remesh_ahead=True))
    assert enhance_mesh(noisy, config).face_count == after.face_count  # the CPU's default
    assert ahead.face_count == pytest.approx(after.face_count, rel=0.02)
    assert (ahead.vertex_count != after.vertex_count
            or not np.allclose(ahead.vertices_m, after.vertices_m))  # not the same path
    assert radial_rms_m(ahead) == pytest.approx(radial_rms_m(after), rel=0.02)
    assert radial_rms_m(ahead) < 0.8 * radial_rms_m(noisy)
