from __future__ import annotations

import numpy as np
import pytest

from pipeline.geometry.mesh import TriangleMesh
from pipeline.reconstruct.quality import MetricsConfig, compare, distance_figures, sample_surface
from tests.pipeline.sphere_scene import CENTRE, RADIUS, ring_cameras, sphere_mesh

CONFIG = MetricsConfig(sample_count=20_000)


def _scaled(mesh: TriangleMesh, factor: float) -> TriangleMesh:
    return TriangleMesh((mesh.vertices_m - CENTRE) * factor + CENTRE, mesh.faces)


def test_samples_lie_on_the_surface_uniformly() -> None:
    points, normals = sample_surface(sphere_mesh(), 20_000)
    radial = points - CENTRE
    np.testing.assert_allclose(np.linalg.norm(radial, axis=1), RADIUS, atol=2e-3)
    # Uniform by area: each hemisphere gets about half.
    assert abs(np.mean(radial[:, 1] > 0) - 0.5) < 0.02
    assert np.mean(np.sum(normals * radial, axis=1) > 0) > 0.999


def test_a_larger_result_has_a_positive_signed_distance() -> None:
    gt = sphere_mesh()
    figures = compare(_scaled(gt, 1.01), gt, ring_cameras(6, 64, 48), CONFIG)
    offset = 0.01 * RADIUS
    assert figures["result_to_gt"]["mean_m"] == pytest.approx(offset, rel=0.05)
    assert figures["result_to_gt"]["rms_m"] == pytest.approx(offset, rel=0.05)
    assert figures["gt_to_result"]["mean_m"] == pytest.approx(-offset, rel=0.05)
    assert figures["coverage_visible"] == 1.0  # 3 mm off, within 5 mm everywhere
    assert figures["normal_error_deg"]["p95"] < 2.0


def test_coverage_counts_only_what_cameras_see() -> None:
    gt = sphere_mesh()
    # A single camera sees less than half of the sphere.
    one = compare(gt, gt, ring_cameras(1, 64, 48), CONFIG)
    assert 0.2 < one["visible_share"] < 0.5
    # A result that is only the half nearest that camera covers all it sees.
    cam = ring_cameras(1, 64, 48)[0]
    assert cam.world_from_depth is not None
    towards = cam.world_from_depth[:3, 3] - CENTRE
    centroids = gt.vertices_m[gt.faces].mean(axis=1)
    half = TriangleMesh(gt.vertices_m, gt.faces[(centroids - CENTRE) @ towards > 0])
    figures = compare(half, gt, [cam], CONFIG)
    assert figures["coverage_visible"] > 0.99
    assert figures["coverage_all"] < 0.6


def test_distance_figures() -> None:
    figures = distance_figures(np.array([-1.0, 1.0, 1.0, -1.0]))
    assert figures == {"mean_m": 0.0, "std_m": 1.0, "rms_m": 1.0, "p95_m": 1.0, "max_m": 1.0}


def test_an_empty_mesh_is_a_value_error() -> None:
    flat = TriangleMesh(np.zeros((3, 3)), np.array([[0, 1, 2]], np.int32))
    with pytest.raises(ValueError, match="mesh"):
        sample_surface(flat, 10)


def test_the_unobserved_part_is_measured_apart() -> None:
    gt = sphere_mesh()
    cam = ring_cameras(1, 64, 48)[0]
    assert cam.world_from_depth is not None
    towards = cam.world_from_depth[:3, 3] - CENTRE
    towards /= np.linalg.norm(towards)
    # The far side pushed out by 1 cm: wrong only where the camera cannot look.
    radial = gt.vertices_m - CENTRE
    far = (radial @ towards < -0.3 * RADIUS)[:, None]
    bulged = TriangleMesh(np.where(far, CENTRE + radial * (1 + 0.01 / RADIUS), gt.vertices_m),
                          gt.faces)
    figures = compare(bulged, gt, [cam], CONFIG)
    observed, unobserved = figures["observed"], figures["unobserved"]
    assert observed["truth_share"] + unobserved["truth_share"] == pytest.approx(1.0)
    assert observed["truth_share"] == pytest.approx(figures["visible_share"])
    assert observed["result_to_gt_rms_m"] < 1e-3
    assert observed["gt_to_result_rms_m"] < 1e-3
    assert unobserved["result_to_gt_rms_m"] > 5e-3
    assert unobserved["gt_to_result_rms_m"] > 5e-3

