"""Depth ICP: depth clouds of a scene seen by a ring of cameras pull misplaced depth cameras
back; a correction beyond the limits is refused with a warning."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from pipeline.calibration.config import CalibrationConfig
from pipeline.calibration.depth_icp import depth_cloud, refine_with_depth
from pipeline.calibration.transforms import from_rotvec
from pipeline.capture import Intrinsics
from pipeline.geometry.mesh import TriangleMesh
from pipeline.synth.render import MeshRaycaster
from pipeline.synth.rig import RigConfig, rig_cameras


@pytest.fixture(scope="module")
def scene_clouds() -> tuple[dict[str, np.ndarray], dict]:
    parts = [trimesh.creation.box((0.5, 0.5, 0.5)), trimesh.creation.icosphere(3, 0.25),
             trimesh.creation.box((0.2, 0.6, 0.3))]
    parts[0].apply_translation((0.15, 0.6, 0.1))
    parts[1].apply_translation((-0.25, 1.2, -0.1))
    parts[2].apply_translation((-0.3, 0.4, 0.35))
    scene: trimesh.Trimesh = trimesh.util.concatenate(parts)  # type: ignore[assignment]
    caster = MeshRaycaster(TriangleMesh(vertices_m=np.asarray(scene.vertices, np.float64),
                                        faces=np.asarray(scene.faces, np.int32)))
    cameras = rig_cameras(RigConfig(camera_count=4, radius_m=1.5, width=320, height=288))
    truth = {c.id: np.asarray(c.world_from_depth) for c in cameras}
    clouds = {c.id: {0: depth_cloud(caster.render(c.depth_intrinsics, truth[c.id]).depth_m,
                                    c.depth_intrinsics, 0.004, stride=1)} for c in cameras}
    return truth, clouds


def test_icp_pulls_shifted_depth_cameras_back(scene_clouds: tuple) -> None:
    truth, clouds = scene_clouds
    rng = np.random.default_rng(1)
    shifted = {c: p @ from_rotvec(np.zeros(3), rng.normal(0, 0.004, 3)) if c != "cam0" else p
               for c, p in truth.items()}
    refined, report = refine_with_depth(clouds, shifted, "cam0", CalibrationConfig())
    before = [np.linalg.norm(shifted[c][:3, 3] - truth[c][:3, 3]) for c in truth]
    after = [np.linalg.norm(refined[c][:3, 3] - truth[c][:3, 3]) for c in truth]
    assert max(before) > 0.004
    assert np.mean(after) < 0.5 * np.mean(before) and max(after) < 0.002
    np.testing.assert_array_equal(refined["cam0"], truth["cam0"])
    assert report["warnings"] == []
    assert all(report["corrections"][c]["correspondences"] > 300 for c in ("cam1", "cam2"))


def test_icp_leaves_true_poses_nearly_alone(scene_clouds: tuple) -> None:
    truth, clouds = scene_clouds
    refined, _ = refine_with_depth(clouds, truth, "cam0", CalibrationConfig())
    for camera_id, pose in truth.items():
        assert np.linalg.norm(refined[camera_id][:3, 3] - pose[:3, 3]) < 0.001


def test_too_large_a_correction_is_refused(scene_clouds: tuple) -> None:
    truth, clouds = scene_clouds
    shifted = dict(truth)
    shifted["cam2"] = truth["cam2"] @ from_rotvec(np.zeros(3), np.array([0.012, 0.0, 0.0]))
    config = CalibrationConfig(icp_max_correction_m=0.005)
    refined, report = refine_with_depth(clouds, shifted, "cam0", config)
    np.testing.assert_array_equal(refined["cam2"], shifted["cam2"])
    assert any("refused for camera cam2" in w for w in report["warnings"])


def test_depth_cloud_normals_face_the_camera_and_fit_the_plane() -> None:
    intrinsics = Intrinsics(320, 288, 208.0, 226.0, 159.5, 143.5)
    v, u = np.mgrid[0:288, 0:320]
    slope = (u - intrinsics.cx) / intrinsics.fx
    depth = np.where(np.abs(slope) < 0.4, 1.5 / (1 - 0.5 * slope), 0).astype(np.float32)
    points, normals = depth_cloud(depth, intrinsics, 0.005)
    plane_normal = np.array([0.5, 0.0, -1.0]) / np.sqrt(1.25)  # towards the camera
    assert len(points) > 1000
    assert np.all(normals @ plane_normal > 0.999)
