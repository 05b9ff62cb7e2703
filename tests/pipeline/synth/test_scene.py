"""Whole synthetic captures: placement, depth on the ground truth, pose errors, determinism."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import open3d as o3d
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.capture import View
from pipeline.geometry.mesh import TriangleMesh
from pipeline.synth.noise import KinectNoiseConfig
from pipeline.synth.render import pixel_rays
from pipeline.synth.rig import RigConfig, rig_cameras
from pipeline.synth.scene import (
    SynthConfig,
    camera_depth_biases_m,
    perturb_pose,
    place_subject,
    sample_mesh,
    synthesize,
    true_cameras,
)
from pipeline.synth.shapes import snowman_mesh

# Small images keep these tests fast; geometry is the same as the full-size rig.
SMALL_RIG = RigConfig(width=160, height=144)


@pytest.fixture(scope="module")
def subject() -> TriangleMesh:
    return snowman_mesh(ring_count=60, azimuth_count=72)


def _points_world(view: View, pose: np.ndarray) -> np.ndarray:
    valid = view.depth_m > 0
    rays = pixel_rays(view.camera.depth_intrinsics)[valid] * view.depth_m[valid, None]
    return rays @ pose[:3, :3].T + pose[:3, 3]


def _distance_to(mesh: TriangleMesh, points: np.ndarray) -> np.ndarray:
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor.from_numpy(mesh.vertices_m.astype(np.float32)),
                        o3d.core.Tensor.from_numpy(mesh.faces.astype(np.uint32)))
    query = o3d.core.Tensor.from_numpy(points.astype(np.float32))
    return scene.compute_distance(query).numpy()


def test_sample_mesh_is_a_closed_figure_of_human_height() -> None:
    mesh = sample_mesh()
    tm = trimesh.Trimesh(mesh.vertices_m, mesh.faces, process=False)
    assert tm.is_watertight and tm.is_winding_consistent and tm.volume > 0
    assert mesh.vertices_m[:, 1].min() == pytest.approx(0.0, abs=1e-9)
    assert mesh.vertices_m[:, 1].max() == pytest.approx(1.8, abs=1e-9)
    assert 50_000 < mesh.face_count < 80_000


@pytest.mark.parametrize("up, long_axis", [("+y", 1), ("+z", 2), ("-x", 0)])
def test_subject_is_uprighted_scaled_and_stood_on_the_floor(up: str, long_axis: int) -> None:
    box = trimesh.creation.box(extents=np.where(np.arange(3) == long_axis, 3.0, 1.0))
    mesh = TriangleMesh(vertices_m=box.vertices + [5.0, -2.0, 1.0],
                        faces=box.faces.astype(np.int32))
    placed = place_subject(mesh, SynthConfig(model_height_m=1.5, up_axis=up))
    lo, hi = placed.vertices_m.min(axis=0), placed.vertices_m.max(axis=0)
    np.testing.assert_allclose([lo[1], hi[1]], [0.0, 1.5], atol=1e-12)
    np.testing.assert_allclose(hi[[0, 2]], 0.25, atol=1e-12)
    np.testing.assert_allclose(lo[[0, 2]], -0.25, atol=1e-12)
    assert placed.vertex_colors is not None and placed.vertex_normals is not None


def test_wide_models_are_scaled_down_to_fit_the_rig() -> None:
    box = trimesh.creation.box(extents=(4.0, 1.0, 1.0))
    mesh = TriangleMesh(vertices_m=box.vertices, faces=box.faces.astype(np.int32))
    placed = place_subject(mesh, SynthConfig(max_radius_m=1.0))
    radius = np.hypot(placed.vertices_m[:, 0], placed.vertices_m[:, 2]).max()
    assert radius == pytest.approx(1.0)
    assert placed.vertices_m[:, 1].max() == pytest.approx(1.0 / np.hypot(2.0, 0.5))
    free = place_subject(mesh, SynthConfig(max_radius_m=None))
    assert free.vertices_m[:, 1].max() == pytest.approx(1.8)
    # The cameras aim at the mid-height of the subject actually placed.
    for cam in true_cameras(placed, SynthConfig()):
        pose = cam.world_from_depth
        assert pose is not None
        target = np.array([0.0, placed.vertices_m[:, 1].max() / 2, 0.0])
        towards = (target - pose[:3, 3]) / np.linalg.norm(target - pose[:3, 3])
        np.testing.assert_allclose(pose[:3, 2], towards, atol=1e-12)


def test_ideal_depth_lies_on_the_ground_truth(subject: TriangleMesh) -> None:
    config = SynthConfig(noise=False, rig=SMALL_RIG)
    meta, views, truth = synthesize(subject, config)
    assert len(views) == 8 and meta.camera_ids == tuple(f"cam{i}" for i in range(8))
    for view in views:
        assert view.depth_m.shape == (144, 160) and view.depth_m.dtype == np.float32
        assert view.color_rgb is not None and view.color_rgb.shape == (144, 160, 3)
        assert (view.depth_m > 0).mean() > 0.05
        pose = meta.camera(view.camera.id).world_from_depth
        assert pose is not None
        assert _distance_to(truth, _points_world(view, pose)).max() < 1e-4
        np.testing.assert_array_equal(view.color_rgb[view.depth_m == 0], 0)


def _depth_edges(depth_m: np.ndarray, jump_m: float = 0.05) -> np.ndarray:
    """Pixels at a depth step (or a silhouette) to a 4-neighbour, and misses."""
    padded = np.pad(depth_m, 1, mode="edge")
    edges = depth_m == 0
    for dy, dx in ((0, 1), (2, 1), (1, 0), (1, 2)):
        neighbour = padded[dy:dy + depth_m.shape[0], dx:dx + depth_m.shape[1]]
        edges |= (np.abs(neighbour - depth_m) > jump_m) | (neighbour == 0)
    return edges


def test_noisy_depth_stays_near_the_ground_truth(subject: TriangleMesh) -> None:
    config = SynthConfig(rig=SMALL_RIG, seed=3)
    meta, views, truth = synthesize(subject, config)
    ideal = synthesize(subject, replace(config, noise=False))[1]
    for view, clean in zip(views, ideal, strict=True):
        pose = meta.camera(view.camera.id).world_from_depth
        assert pose is not None
        inner = ~_depth_edges(clean.depth_m)
        kept = (view.depth_m > 0)[inner].mean()
        assert 0.9 < kept < 1.0
        distance = _distance_to(truth, _points_world(view, pose))
        # Away from depth edges: sensor noise (2-3 mm here) plus a few mm of camera bias.
        inner_distance = distance[inner[view.depth_m > 0]]
        assert np.median(inner_distance) < 0.006
        assert inner_distance.max() < 0.025
        # At the edges some pixels fly off the surface.
        assert distance.max() > 0.05


def test_each_cameras_range_offset_is_the_one_drawn(subject: TriangleMesh) -> None:
    """Noise with no random part: each camera's range is off by `camera_depth_biases_m`."""
    model = KinectNoiseConfig(sigma_base_m=0.0, sigma_per_m=0.0, quantization_m=0.0,
                              bias_std_m=0.004)
    config = SynthConfig(rig=SMALL_RIG, seed=5, camera_count=3, noise_model=model)
    views = synthesize(subject, config)[1]
    ideal = synthesize(subject, replace(config, noise=False))[1]
    biases = camera_depth_biases_m(config, 3)
    assert len(set(biases)) == 3 and max(map(abs, biases)) > 0.001
    for view, clean, bias in zip(views, ideal, biases, strict=True):
        both = (view.depth_m > 0) & (clean.depth_m > 0) & ~_depth_edges(clean.depth_m)
        rays = pixel_rays(view.camera.depth_intrinsics)[both]
        range_change = (view.depth_m - clean.depth_m)[both] * np.linalg.norm(rays, axis=1)
        np.testing.assert_allclose(range_change, bias, atol=1e-5)


@settings(max_examples=20, deadline=None)
@given(rot_deg=st.floats(0.0, 10.0), trans_m=st.floats(0.0, 0.1), seed=st.integers(0, 99))
def test_perturbed_pose_moves_by_the_asked_amount(rot_deg: float, trans_m: float,
                                                  seed: int) -> None:
    true = rig_cameras(RigConfig())[3].world_from_depth
    assert true is not None
    moved = perturb_pose(true, rot_deg, trans_m, np.random.default_rng(seed))
    relative = true[:3, :3].T @ moved[:3, :3]
    angle = math.degrees(math.acos(np.clip((np.trace(relative) - 1) / 2, -1, 1)))
    assert angle == pytest.approx(rot_deg, abs=1e-5)
    assert np.linalg.norm(moved[:3, 3] - true[:3, 3]) == pytest.approx(trans_m, abs=1e-12)
    np.testing.assert_allclose(moved[:3, :3].T @ moved[:3, :3], np.eye(3), atol=1e-12)


def test_pose_error_applies_to_written_extrinsics_only(subject: TriangleMesh) -> None:
    clean = SynthConfig(rig=SMALL_RIG, camera_count=3, seed=5)
    off = replace(clean, pose_error_rot_deg=2.0, pose_error_trans_m=0.01)
    meta_clean, views_clean, truth = synthesize(subject, clean)
    meta_off, views_off, _ = synthesize(subject, off)
    for cam_true, cam_clean in zip(true_cameras(truth, clean), meta_clean.cameras, strict=True):
        np.testing.assert_array_equal(cam_true.world_from_depth, cam_clean.world_from_depth)
    for cam_clean, cam_off in zip(meta_clean.cameras, meta_off.cameras, strict=True):
        a, b = cam_clean.world_from_depth, cam_off.world_from_depth
        assert a is not None and b is not None
        assert np.linalg.norm(b[:3, 3] - a[:3, 3]) == pytest.approx(0.01)
        cos = (np.trace(a[:3, :3].T @ b[:3, :3]) - 1) / 2
        assert math.degrees(math.acos(cos)) == pytest.approx(2.0, abs=1e-5)
    for a_view, b_view in zip(views_clean, views_off, strict=True):
        np.testing.assert_array_equal(a_view.depth_m, b_view.depth_m)


def test_frames_and_seeds(subject: TriangleMesh) -> None:
    config = SynthConfig(rig=SMALL_RIG, camera_count=2, frame_count=3, seed=11)
    meta, views, _ = synthesize(subject, config)
    assert meta.frame_indices == (0, 1, 2)
    assert [(v.camera.id, v.frame_index) for v in views] == [
        ("cam0", 0), ("cam0", 1), ("cam0", 2), ("cam1", 0), ("cam1", 1), ("cam1", 2)]
    assert not np.array_equal(views[0].depth_m, views[1].depth_m)
    again = synthesize(subject, config)[1]
    for a, b in zip(views, again, strict=True):
        np.testing.assert_array_equal(a.depth_m, b.depth_m)
    other = synthesize(subject, replace(config, seed=12))[1]
    assert not np.array_equal(views[0].depth_m, other[0].depth_m)


def test_floor_is_rendered_but_not_ground_truth(subject: TriangleMesh) -> None:
    config = SynthConfig(rig=SMALL_RIG, camera_count=1, noise=False)
    _, alone, truth = synthesize(subject, config)
    _, floored, truth_floor = synthesize(subject, replace(config, floor=True))
    assert (floored[0].depth_m > 0).sum() > (alone[0].depth_m > 0).sum()
    assert truth_floor.vertex_count == truth.vertex_count


def test_progress_reaches_one(subject: TriangleMesh) -> None:
    seen: list[float] = []
    synthesize(subject, SynthConfig(rig=SMALL_RIG, camera_count=4), progress=seen.append)
    assert seen == [0.25, 0.5, 0.75, 1.0]


@pytest.mark.parametrize("field, value", [("model_height_m", 0.0), ("up_axis", "up"),
                                          ("frame_count", 0), ("pose_error_rot_deg", -1.0)])
def test_bad_config_names_the_field(field: str, value: object) -> None:
    with pytest.raises(ValueError, match=field):
        SynthConfig(**{field: value})  # type: ignore[arg-type]
