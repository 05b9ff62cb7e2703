"""Multi-camera extrinsic calibration from ChArUco captures (docs/architecture.md, step 3).

Entry point: ``calibrate(capture, config, progress) -> (world_from_depth, report)``.
"""

from pipeline.calibration.calibrate import CaptureSource, calibrate
from pipeline.calibration.config import CalibrationConfig

__all__ = ["CalibrationConfig", "CaptureSource", "calibrate"]
