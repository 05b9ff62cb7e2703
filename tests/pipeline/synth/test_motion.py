"""Synthetic sequences: each frame's depth is the truth of that frame; static frames differ
by noise alone; timestamps follow the frame rate."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.synth.motion import MotionConfig, synthesize_sequence, world_from_subject
from pipeline.synth.render import MeshRaycaster
from pipeline.synth.rig import RigConfig
from pipeline.synth.scene import SynthConfig, true_cameras
from pipeline.synth.shapes import snowman_mesh

SMALL = SynthConfig(camera_count=2, frame_count=3, rig=RigConfig(width=96, height=80))


def test_rigid_frames_show_the_truth_of_each_frame() -> None:
    config = SynthConfig(camera_count=2, frame_count=3, noise=False,
                         rig=RigConfig(width=96, height=80))
    motion = MotionConfig(kind="rigid", frame_rate_hz=10, turn_deg_per_s=90)
    meta, views, truth = synthesize_sequence(snowman_mesh(), config, motion)
    assert [f.timestamp_us for f in meta.frames] == [0, 100_000, 200_000]
    assert truth.frame_count == 3
    cameras = true_cameras(truth.subject, config)
    by_key = {(v.camera.id, v.frame_index): v for v in views}
    for frame in range(3):
        moved = MeshRaycaster(truth.mesh(frame))
        for cam in cameras:
            assert cam.world_from_depth is not None
            expected = moved.render(cam.depth_intrinsics, cam.world_from_depth).depth_m
            got = by_key[(cam.id, frame)].depth_m
            assert (got > 0).sum() > 500
            np.testing.assert_allclose(got, expected, atol=1e-4)
    assert not np.allclose(by_key[("cam0", 0)].depth_m, by_key[("cam0", 2)].depth_m)


def test_static_frames_differ_by_noise_alone() -> None:
    meta, views, truth = synthesize_sequence(snowman_mesh(), SMALL, MotionConfig())
    first, second = [v for v in views if v.camera.id == "cam0"][:2]
    hit = (first.depth_m > 0) & (second.depth_m > 0)
    difference_m = np.abs(first.depth_m[hit] - second.depth_m[hit])
    assert 0 < float(np.median(difference_m)) < 0.01  # fresh noise, same surface
    np.testing.assert_array_equal(truth.world_from_subject, np.stack([np.eye(4)] * 3))
    assert meta.frame_indices == (0, 1, 2)


def test_motion_settings_are_checked() -> None:
    with pytest.raises(ValueError, match="kind"):
        MotionConfig(kind="dance")
    with pytest.raises(ValueError, match="frame_rate_hz"):
        MotionConfig(frame_rate_hz=0)
    with pytest.raises(ValueError, match="floor"):
        synthesize_sequence(snowman_mesh(), SynthConfig(floor=True), MotionConfig(kind="rigid"))
    pose = world_from_subject(MotionConfig(kind="rigid", sway_frequency_hz=0.25), 1.0)
    assert pose[0, 3] == pytest.approx(0.1)


def test_an_articulated_bow_bends_the_upper_part_alone() -> None:
    config = SynthConfig(camera_count=2, frame_count=2, noise=False,
                         rig=RigConfig(width=96, height=80))
    motion = MotionConfig(kind="articulated", frame_rate_hz=2, bow_frequency_hz=0.5)
    meta, views, truth = synthesize_sequence(snowman_mesh(), config, motion)
    assert truth.bow_rad is not None and truth.bow_rad[0] == 0.0
    assert truth.bow_rad[1] == pytest.approx(np.radians(25.0))  # a quarter period: the peak
    standing, bowed = truth.mesh(0).vertices_m, truth.mesh(1).vertices_m
    np.testing.assert_allclose(standing, truth.subject.vertices_m)
    low = standing[:, 1] < truth.joint_y_m - truth.joint_blend_m
    high = standing[:, 1] > truth.joint_y_m + truth.joint_blend_m
    np.testing.assert_allclose(bowed[low], standing[low])
    assert np.abs(bowed[high] - standing[high]).max() > 0.1
    top = np.argmax(standing[:, 1])  # rigidly turned above the band: its distance to the joint
    joint = np.array([0.0, truth.joint_y_m, 0.0])
    assert np.linalg.norm(bowed[top] - joint) == pytest.approx(
        np.linalg.norm(standing[top] - joint))
    by_key = {(v.camera.id, v.frame_index): v.depth_m for v in views}
    assert not np.array_equal(by_key[("cam0", 0)], by_key[("cam0", 1)])
    assert len(by_key) == 4 and meta.frame_indices == (0, 1)


@pytest.mark.parametrize("kind", ["static", "rigid", "articulated"])
def test_by_frame_gives_the_same_frames_frame_set_by_frame_set_from_any_first(kind: str
                                                                              ) -> None:
    config = SynthConfig(camera_count=2, frame_count=3, noise=False,
                         rig=RigConfig(width=48, height=40))
    motion = MotionConfig(kind=kind, frame_rate_hz=10, turn_deg_per_s=90)
    _, by_camera, _ = synthesize_sequence(snowman_mesh(), config, motion)
    expected = {(v.camera.id, v.frame_index): v.depth_m for v in by_camera}
    _, by_frame, _ = synthesize_sequence(snowman_mesh(), config, motion, by_frame=True)
    views = list(by_frame)
    assert [(v.frame_index, v.camera.id) for v in views] == \
        [(f, c) for f in range(3) for c in ("cam0", "cam1")]
    for view in views:
        np.testing.assert_array_equal(view.depth_m, expected[(view.camera.id, view.frame_index)])
    _, resumed, _ = synthesize_sequence(snowman_mesh(), config, motion, by_frame=True,
                                        first_frame=2)
    assert [(v.frame_index, v.camera.id) for v in resumed] == [(2, "cam0"), (2, "cam1")]
    with pytest.raises(ValueError, match="first_frame"):
        synthesize_sequence(snowman_mesh(), config, motion, first_frame=4)
