"""The synthetic rig: rigid poses, every camera aimed at the subject, the Azure Kinect layout."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.synth.rig import RigConfig, look_at, rig_cameras, rig_intrinsics


@settings(max_examples=60, deadline=None)
@given(count=st.integers(1, 24), radius=st.floats(0.5, 5.0),
       upper=st.floats(0.1, 4.0), lower=st.floats(0.1, 4.0),
       target_y=st.floats(0.2, 1.5), offset=st.floats(-360.0, 360.0))
def test_poses_are_rigid_and_face_the_target(count: int, radius: float, upper: float,
                                             lower: float, target_y: float,
                                             offset: float) -> None:
    config = RigConfig(camera_count=count, radius_m=radius, upper_height_m=upper,
                       lower_height_m=lower, target_m=(0.0, target_y, 0.0),
                       azimuth_offset_deg=offset)
    cameras = rig_cameras(config)
    assert len(cameras) == count
    assert len({cam.id for cam in cameras}) == count
    target = np.array(config.target_m)
    intr = rig_intrinsics(config)
    for cam in cameras:
        pose = cam.world_from_depth
        assert pose is not None
        rotation = pose[:3, :3]
        np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-12)
        assert np.linalg.det(rotation) == pytest.approx(1.0, abs=1e-12)
        np.testing.assert_array_equal(pose[3], [0, 0, 0, 1])
        # The target lies on the optical axis, in front, and projects to the principal point.
        target_cam = np.linalg.inv(pose) @ np.append(target, 1.0)
        assert target_cam[2] > 0
        u = intr.fx * target_cam[0] / target_cam[2] + intr.cx
        v = intr.fy * target_cam[1] / target_cam[2] + intr.cy
        assert u == pytest.approx(intr.cx, abs=1e-9)
        assert v == pytest.approx(intr.cy, abs=1e-9)
        # Images are upright: x stays horizontal, image down points down the world.
        assert abs(rotation[1, 0]) < 1e-12
        assert rotation[1, 1] < 0
        assert np.hypot(pose[0, 3], pose[2, 3]) == pytest.approx(radius)


def test_default_rig_is_two_rings_of_four_offset_by_45_degrees() -> None:
    cameras = rig_cameras(RigConfig())
    centres = np.array([cam.world_from_depth[:3, 3] for cam in cameras])  # type: ignore[index]
    np.testing.assert_allclose(centres[:4, 1], 2.0)
    np.testing.assert_allclose(centres[4:, 1], 1.0)
    azimuths = np.degrees(np.arctan2(centres[:, 0], centres[:, 2])) % 360
    np.testing.assert_allclose(np.sort(azimuths[:4]), [0, 90, 180, 270], atol=1e-9)
    np.testing.assert_allclose(np.sort(azimuths[4:]), [45, 135, 225, 315], atol=1e-9)


def test_default_rig_sees_a_standing_person_in_range() -> None:
    """A 1.8 m subject within 0.45 m of the axis is inside every image and the sensor range."""
    config = RigConfig()
    intr = rig_intrinsics(config)
    angle = np.linspace(0, 2 * np.pi, 72, endpoint=False)
    corners = np.array([[0.45 * np.sin(a), y, 0.45 * np.cos(a), 1.0] for a in angle
                        for y in (0.0, 1.8)])
    for cam in rig_cameras(config):
        assert cam.world_from_depth is not None
        local = (np.linalg.inv(cam.world_from_depth) @ corners.T).T
        assert (local[:, 2] > 0.5).all() and (local[:, 2] < 3.86).all()
        u = intr.fx * local[:, 0] / local[:, 2] + intr.cx
        v = intr.fy * local[:, 1] / local[:, 2] + intr.cy
        assert ((u >= 0) & (u <= intr.width - 1) & (v >= 0) & (v <= intr.height - 1)).all()


def test_intrinsics_match_the_nfov_unbinned_mode() -> None:
    intr = rig_intrinsics(RigConfig())
    assert (intr.width, intr.height) == (640, 576)
    assert math.degrees(2 * math.atan(320 / intr.fx)) == pytest.approx(75.0)
    assert math.degrees(2 * math.atan(288 / intr.fy)) == pytest.approx(65.0)
    assert (intr.cx, intr.cy) == (319.5, 287.5)
    assert not intr.has_distortion


@pytest.mark.parametrize("eye", [(0.0, 3.0, 0.0), (0.0, -1.0, 0.0)])
def test_look_at_refuses_vertical_views(eye: tuple[float, float, float]) -> None:
    with pytest.raises(ValueError, match="vertical"):
        look_at(np.array(eye), np.array([0.0, 1.0, 0.0]))


@pytest.mark.parametrize("field, value", [("camera_count", 0), ("radius_m", 0.0),
                                          ("fov_x_deg", 180.0)])
def test_bad_rig_config_names_the_field(field: str, value: float) -> None:
    with pytest.raises(ValueError, match=field):
        RigConfig(**{field: value})  # type: ignore[arg-type]
