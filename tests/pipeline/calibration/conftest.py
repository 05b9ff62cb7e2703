"""A small synthetic calibration capture on disk, shared by the end-to-end tests."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from pipeline.capture import CaptureMeta, View
from pipeline.io.capture_io import write_capture
from pipeline.synth.rig import RigConfig, rig_cameras
from pipeline.synth.target import TargetSynthConfig, synthesize_calibration


@dataclass(frozen=True)
class SmallCapture:
    path: Path
    meta: CaptureMeta
    views: list[View]
    truth: dict[str, np.ndarray]


def small_config(**changes: object) -> TargetSynthConfig:
    """4 cameras close in, smaller images: seconds to render, still realistic optics."""
    values: dict[str, object] = {"frame_count": 8, "color_width": 800, "color_height": 450,
                                 "color_fov_x_deg": 80.0, "seed": 3}
    values.update(changes)
    return TargetSynthConfig(**values)  # type: ignore[arg-type]


def small_rig() -> list:
    return rig_cameras(RigConfig(camera_count=4, radius_m=1.5, width=320, height=288,
                                 upper_height_m=1.6, lower_height_m=0.9))


@pytest.fixture(scope="session")
def small_capture(tmp_path_factory: pytest.TempPathFactory) -> SmallCapture:
    meta, views, truth = synthesize_calibration(small_config(), cameras=small_rig())
    rendered = list(views)
    path = tmp_path_factory.mktemp("calib") / "capture"
    write_capture(path, meta, rendered)
    return SmallCapture(path, meta, rendered, truth)
