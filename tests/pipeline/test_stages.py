from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from pipeline.geometry.mesh import TriangleMesh
from pipeline.io.capture_io import open_capture, write_capture
from pipeline.reconstruct.quality import MetricsConfig, compare
from pipeline.stage_config import ReconstructConfig, config_from_options
from pipeline.stages import mesh_from_artifacts, planned_stages, reconstruct, run_stage
from tests.pipeline.sphere_scene import (
    distance_to_sphere,
    ring_cameras,
    sphere_mesh,
    sphere_meta,
    sphere_views,
)

BIASES = [0.003, -0.002, 0.004, 0.0, -0.003, 0.001]


@pytest.fixture(scope="module")
def sphere_capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    cams = ring_cameras(6, 320, 288)
    out = tmp_path_factory.mktemp("sphere") / "capture"
    write_capture(out, sphere_meta(cams), sphere_views(cams, BIASES, noise_m=0.001))
    return out


@pytest.fixture(scope="module")
def whole_run(sphere_capture: Path) -> tuple[TriangleMesh, dict, list[str], list[float]]:
    stage_names: list[str] = []
    fractions: list[float] = []
    with open_capture(sphere_capture) as capture:
        mesh, report = reconstruct(capture, ReconstructConfig(), fractions.append,
                                   stage_names.append)
    return mesh, report, stage_names, fractions


def test_a_sphere_from_analytic_depth_maps_comes_back(
        sphere_capture: Path, whole_run: tuple[TriangleMesh, dict, list[str], list[float]]
) -> None:
    mesh, report, stage_names, fractions = whole_run
    cameras = ring_cameras(6, 320, 288)
    assert stage_names == list(planned_stages(ReconstructConfig()))
    assert "enhance" not in stage_names  # off unless asked
    assert fractions == sorted(fractions) and fractions[-1] == pytest.approx(1.0)
    d = distance_to_sphere(mesh.vertices_m)
    assert np.sqrt(np.mean(d**2)) < 0.0008
    figures = compare(mesh, sphere_mesh(), cameras, MetricsConfig(sample_count=20_000))
    assert figures["result_to_gt"]["rms_m"] < 0.0008
    assert figures["coverage_visible"] > 0.97
    # On a lone sphere a camera's range offset and a move towards the centre look alike, so
    # the split between them is the priors' (test_align checks offsets on a richer scene).
    assert set(report["stage_stats"]["align"]["depth_offset_mm"]) == {c.id for c in cameras}
    assert report["triangles"] == mesh.face_count > 1000
    assert set(report["stage_seconds"]) == set(stage_names)
    assert mesh.vertex_colors is not None and np.all(mesh.vertex_colors == 200)
    assert mesh.vertex_normals is not None


def test_stage_by_stage_with_merged_artifacts_gives_the_same_mesh(
        sphere_capture: Path, whole_run: tuple[TriangleMesh, dict, list[str], list[float]]
) -> None:
    config = ReconstructConfig()
    artifacts: dict[str, np.ndarray] = {}
    with open_capture(sphere_capture) as capture:
        for name in planned_stages(config):
            out = run_stage(name, capture, artifacts, config)
            assert all(isinstance(v, np.ndarray) for v in out.values())
            # What a worker stores and loads (npz, no pickles) must round-trip.
            assert all(v.dtype != object for v in out.values())
            artifacts.update(out)
    mesh, whole = mesh_from_artifacts(artifacts), whole_run[0]
    # Equal up to the summation order of the multi-threaded Poisson solve.
    assert abs(mesh.face_count - whole.face_count) <= 0.01 * whole.face_count
    figures = compare(mesh, whole, [], MetricsConfig(sample_count=5000))
    assert figures["result_to_gt"]["p95_m"] < 2e-4


def test_a_rig_overrides_the_capture_poses(sphere_capture: Path, tmp_path: Path) -> None:
    cams = ring_cameras(6, 320, 288)
    moved = [dataclasses.replace(c, world_from_depth=None) for c in cams]
    out = tmp_path / "unposed"
    views = sphere_views(cams, noise_m=0.0)
    write_capture(out, sphere_meta(moved), [dataclasses.replace(v, camera=m)
                                            for v, m in zip(views, moved, strict=True)])
    with open_capture(out) as capture:
        with pytest.raises(ValueError, match="world_from_depth"):
            run_stage("filter", capture, {}, ReconstructConfig())
        rig = {c.id: np.asarray(c.world_from_depth).tolist() for c in cams}
        config = config_from_options({"world_from_depth": rig})
        artifacts: dict[str, np.ndarray] = {}
        for name in ("filter", "align", "register"):
            artifacts.update(run_stage(name, capture, artifacts, config))
    points = artifacts["points_world"]
    assert len(points) > 10_000
    assert np.percentile(np.abs(distance_to_sphere(points)), 95) < 0.002
    with open_capture(sphere_capture) as capture, pytest.raises(ValueError, match="frame"):
        run_stage("filter", capture, {}, config_from_options({"frame_index": 7}))


def test_unknown_stages_and_missing_inputs_are_value_errors(sphere_capture: Path) -> None:
    with open_capture(sphere_capture) as capture:
        with pytest.raises(ValueError, match="stage"):
            run_stage("polish", capture, {}, ReconstructConfig())
        with pytest.raises(ValueError, match="points_world"):
            run_stage("refine", capture, {}, ReconstructConfig())
    with pytest.raises(ValueError, match="vertices_m"):
        mesh_from_artifacts({})


def test_the_enhance_stage_asks_for_its_networks_only_where_it_enhances(
        sphere_capture: Path, whole_run: tuple[TriangleMesh, dict, list[str], list[float]],
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A worker's kept networks (loading them costs a fresh worker seconds) are asked for only
    where the mesh is noisy enough to enhance; a clean mesh comes back as it was. The noise
    is measured once a mesh, by the stage, not again by `enhance_mesh`'s gate."""
    import pipeline.enhance.noise_level as noise_level
    from pipeline.enhance import EnhanceConfig
    from pipeline.enhance.networks import EnhanceNetworks, load_networks
    from pipeline.enhance.training.data import noisy_along_normals

    enhancement = EnhanceConfig(method="regressor", resolution=32, remesh_iterations=0)
    config = dataclasses.replace(ReconstructConfig(), enhancement=enhancement)
    asked: list[EnhanceConfig] = []

    def networks() -> EnhanceNetworks:
        asked.append(enhancement)
        return load_networks(enhancement)

    measured: list[int] = []
    measure = noise_level.noise_to_edge_ratio

    def counted(*args, **kwargs) -> float:  # type: ignore[no-untyped-def]
        measured.append(1)
        return measure(*args, **kwargs)

    monkeypatch.setattr(noise_level, "noise_to_edge_ratio", counted)
    clean = whole_run[0]
    noisy = noisy_along_normals(clean, 0.01, np.random.default_rng(0))
    with open_capture(sphere_capture) as capture:
        left = run_stage("enhance", capture, {"vertices_m": clean.vertices_m,
                                              "faces": clean.faces}, config, None, networks)
        assert asked == []
        stats = json.loads(str(left["stats_enhance"]))
        assert stats["skipped_as_clean"] is True and stats["noise_ratio"] < 0.05
        assert stats["max_offset_m"] == 0.0
        assert np.array_equal(left["vertices_m"], clean.vertices_m)
        moved = run_stage("enhance", capture, {"vertices_m": noisy.vertices_m,
                                               "faces": noisy.faces}, config, None, networks)
    assert asked == [enhancement]
    assert len(measured) == 2  # one a mesh
    assert json.loads(str(moved["stats_enhance"]))["skipped_as_clean"] is False
    assert not np.allclose(moved["vertices_m"], noisy.vertices_m)


def test_the_enhance_stage_reports_its_self_check(
        sphere_capture: Path, whole_run: tuple[TriangleMesh, dict, list[str], list[float]]
) -> None:
    """With `self_check` on, the stage's figures tell the check's decision and its two
    scores; off, they say there was none."""
    from pipeline.enhance import EnhanceConfig
    from pipeline.enhance.training.data import noisy_along_normals

    noisy = noisy_along_normals(whole_run[0], 0.01, np.random.default_rng(0))
    artifacts = {"vertices_m": noisy.vertices_m, "faces": noisy.faces}
    stats = {}
    for checked in (True, False):
        enhancement = EnhanceConfig(method="regressor", resolution=32, remesh_iterations=0,
                                    self_check=checked)
        config = dataclasses.replace(ReconstructConfig(), enhancement=enhancement)
        with open_capture(sphere_capture) as capture:
            out = run_stage("enhance", capture, artifacts, config, None)
        stats[checked] = json.loads(str(out["stats_enhance"]))["self_check"]
    assert stats[False] is None
    check = stats[True]
    assert check["networks_help"] == (check["with_networks_rms_mm"]
                                      < check["without_networks_rms_mm"])
    assert 0 < check["without_networks_rms_mm"] < 10


def test_a_capture_reconstructs_to_the_same_mesh_each_time(
        sphere_capture: Path, whole_run: tuple[TriangleMesh, dict, list[str], list[float]]
) -> None:
    """The report's config hash names one mesh: every stage is deterministic, the Poisson
    solve on one thread (`MeshingConfig.poisson_threads`)."""
    with open_capture(sphere_capture) as capture:
        again, _ = reconstruct(capture, ReconstructConfig())
    assert np.array_equal(again.faces, whole_run[0].faces)
    assert np.array_equal(again.vertices_m, whole_run[0].vertices_m)
