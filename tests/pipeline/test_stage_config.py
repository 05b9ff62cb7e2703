"""Job options become a validated reconstruction config, or a ValueError naming the option."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from pipeline.stage_config import (
    ReconstructConfig,
    config_from_options,
    config_hash,
    parse_world_from_depth,
)


def test_options_become_a_validated_config() -> None:
    config = config_from_options({"enhance": True, "target_edge_length_m": 0.02,
                                  "voxel_size_m": 0.01, "frame_index": 0,
                                  "meshing": {"poisson_depth": 8}})
    assert config.enhance and config.target_edge_length_m == 0.02
    assert config.voxel_refine.voxel_size_m == 0.01 and config.meshing.poisson_depth == 8
    assert config_hash(config) == config_hash(dataclasses.replace(config))
    assert config_hash(config) != config_hash(ReconstructConfig())
    assert config_from_options({}) == ReconstructConfig()


@pytest.mark.parametrize("options, field", [
    ({"bogus": 1}, "bogus"),
    ({"target_edge_length_m": -1.0}, "target_edge_length_m"),
    ({"target_edge_length_m": "big"}, "target_edge_length_m"),
    ({"voxel_size_m": 0}, "voxel_size_m"),
    ({"frame_index": -1}, "frame_index"),
    ({"enhance": "yes"}, "enhance"),
    ({"meshing": {"poisson_depth": 99}}, "meshing"),
    ({"meshing": {"nope": 1}}, "meshing.nope"),
    ({"world_from_depth": {"cam0": [[1, 0], [0, 1]]}}, "world_from_depth.cam0"),
    ({"world_from_depth": {"cam0": np.diag([2.0, 1, 1, 1]).tolist()}}, "world_from_depth.cam0"),
])
def test_bad_options_are_value_errors_naming_the_option(options: dict, field: str) -> None:
    with pytest.raises(ValueError, match=field.replace(".", r"\.")):
        config_from_options(options)


def _rigid(quaternion: list[float], translation_m: list[float]) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_quat(quaternion).as_matrix()
    pose[:3, 3] = translation_m
    return pose


_QUATERNIONS = st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(
    lambda q: np.linalg.norm(q) > 0.1)
_TRANSLATIONS = st.lists(st.floats(-5, 5), min_size=3, max_size=3)


@given(q=_QUATERNIONS, t=_TRANSLATIONS)
def test_any_rigid_pose_is_kept_exactly(q: list[float], t: list[float]) -> None:
    pose = _rigid(q, t)
    ((camera_id, values),) = parse_world_from_depth({"cam3": pose.tolist()})
    assert camera_id == "cam3"
    assert np.array_equal(np.reshape(values, (4, 4)), pose)


@given(q=_QUATERNIONS, t=_TRANSLATIONS, scale=st.floats(1.01, 3.0))
def test_a_scaled_or_mirrored_pose_is_refused(q: list[float], t: list[float], scale: float
                                              ) -> None:
    pose = _rigid(q, t)
    scaled = pose @ np.diag([scale, 1.0, 1.0, 1.0])
    mirrored = pose @ np.diag([-1.0, 1.0, 1.0, 1.0])
    for bad in (scaled, mirrored):
        with pytest.raises(ValueError, match="cam1: not a rigid transform"):
            parse_world_from_depth({"cam1": bad.tolist()})
