"""Settings of the multi-camera calibration (one frozen dataclass)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class CalibrationConfig:
    """How the ChArUco calibration detects, chains, refines and reports."""

    min_corners_per_view: int = 6
    """Views with fewer ChArUco corners are ignored (PnP needs a spread of points)."""
    reference_camera: str | None = None
    """Camera whose depth frame defines the world (flipped to +Y up); None: the first camera
    in the capture that sees the target."""
    max_iterations: int = 12
    """Upper bound on the refine / reject rounds before the bundle adjustment."""
    subset_fraction: float = 0.7
    """Share of the frames drawn at random to refine the camera poses in each round."""
    convergence_tolerance: float = 0.01
    """The rounds stop when the error falls by less than this fraction of itself."""
    outlier_factor: float = 4.0
    """A view is an outlier when its RMS exceeds this many robust sigmas above the median."""
    outlier_min_px: float = 1.0
    """... and exceeds this RMS in pixels (noise-free views are never rejected)."""
    loss_scale_px: float = 1.0
    """Huber loss scale of the least-squares solvers, in pixels of residual."""
    seed: int = 0
    """Seed of the random frame subsets, so runs are reproducible."""
    min_views_warning: int = 4
    """Cameras that used fewer views than this get a warning in the report."""
    max_rms_warning_px: float = 1.0
    """Cameras whose reprojection RMS exceeds this get a warning in the report."""
    workers: int = 2
    """Threads decoding and detecting images in parallel (OpenCV releases the GIL)."""
    icp: bool = False
    """Refine the depth cameras by ICP between their depth clouds after the ChArUco fit."""
    icp_rotation: bool = False
    """Let the depth ICP turn cameras too (default: it only moves them; see depth_icp.py)."""
    icp_max_distance_m: float = 0.02
    """Largest point-to-plane correspondence distance of the depth ICP."""
    icp_voxel_size_m: float = 0.005
    """Voxel size the depth clouds are thinned to before the ICP."""
    icp_max_correction_m: float = 0.03
    """ICP corrections moving a camera further than this are refused (with a warning)."""
    icp_max_correction_deg: float = 2.0
    """ICP corrections rotating a camera more than this are refused (with a warning)."""

    def __post_init__(self) -> None:
        if self.min_corners_per_view < 4:
            raise ValueError("CalibrationConfig.min_corners_per_view must be at least 4")
        if not 0.0 < self.subset_fraction <= 1.0:
            raise ValueError("CalibrationConfig.subset_fraction must be in (0, 1]")
        if self.max_iterations < 1:
            raise ValueError("CalibrationConfig.max_iterations must be at least 1")
        if self.workers < 1:
            raise ValueError("CalibrationConfig.workers must be at least 1")
