"""Alignment of the cameras on their overlaps: per-camera range offsets and pose touch-ups,
bounded by the sensor's error budget and by what the overlaps show.

Time-of-flight cameras measure range with a small constant offset per unit (a few mm for
the Azure Kinect), which no extrinsic calibration removes, and a calibrated rig keeps pose
residuals of a fraction of a degree and a few millimetres. Both leave the cameras' surfaces
apart where they overlap, and whichever camera a region is taken from shows its own error.
A robust least-squares solve over the overlaps (`align_solve`) finds a range offset and a
small pose correction per camera; matches are then redrawn and the solve repeated, as in
multi-view ICP.

A correction is a claim about the sensor, so it is kept only when it is plausible and shown:

* **Budget.** A correction may move what its camera sees by no more than the sensor's
  systematic error at that distance (Azure Kinect: 11 mm + 0.1 % of the distance). Beyond
  it, the disagreement is not the sensor's and the solve would bend the scene to fit noise
  or a poor calibration: the correction is refused with a warning and the camera kept as
  captured.
* **Evidence.** Solved from one half of the overlaps (alternate 5 cm cubes of the world),
  most of the change in the gaps that the corrections predict must show in the other half's
  gaps (and the other way round), pooled over each camera's overlaps. A solve bends to the
  noise and mismatches of the samples it is given; a true offset or pose error shows in the
  held-out ones as well. (An error smooth across the whole image shows in both halves
  whatever its cause; the budget bounds those.)
* **The simpler model first.** Pose touch-ups are estimated only when, solved from one half,
  they explain the other half's gaps better than range offsets alone do, by more than twice
  the gain's standard error. On the thin overlaps of a ring an offset and a small turn bend
  a strip alike; the solve would share a pure offset between them and swing the camera's far
  side, which no overlap sees.

Refusals are decided one camera at a time, the worst first, and the rest solved again: a
camera beyond the budget leaves the solve, one whose correction is not shown stays in as
captured.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from pipeline.capture import Intrinsics
from pipeline.reconstruct.align_evidence import heldout_confirmation, poses_shown
from pipeline.reconstruct.align_solve import (
    Matches,
    SampledCamera,
    apply_correction,
    pair_matches,
    sample_camera,
    shifts_m,
    solve,
)

FloatArray = NDArray[np.float64]

APPLIED = "applied"
BEYOND_BUDGET = "refused: beyond the sensor's error budget"
NOT_SUPPORTED = "not applied: the overlaps do not support it"
NO_OVERLAP = "not applied: no overlap with a camera left in the solve"
OFF = "off"


@dataclass(frozen=True)
class AlignConfig:
    """How cameras are aligned on their overlaps."""

    offsets: bool = True
    """Estimate per-camera range offsets."""
    poses: bool = True
    """Also touch up the camera poses (small rotations and translations)."""
    sample_step_px: int = 4
    """Every this many pixels (in x and y) of each camera are matched against the others."""
    edge_margin_px: int = 3
    """Pixels this close to a hole or silhouette are not matched (their depth is biased by
    mixed returns and one-sided filtering)."""
    gate_m: float = 0.02
    """Matches farther apart than this along the view ray are different surfaces."""
    max_normal_angle_deg: float = 30.0
    """Matches whose two normals differ by more than this are dropped."""
    max_incidence_deg: float = 65.0
    """Matches seen more obliquely than this by either camera are dropped."""
    huber_m: float = 0.002
    """Residuals beyond this weigh less (Huber loss), metres."""
    offset_prior_m: float = 0.01
    """Standard deviation of the zero-mean prior on each range offset, metres."""
    rotation_prior_deg: float = 0.25
    """Standard deviation of the zero-mean prior on each pose rotation, degrees (a rig
    calibration's residuals; it keeps directions the overlaps barely see, such as a turn
    about a round subject's axis, where they are)."""
    translation_prior_m: float = 0.003
    """Standard deviation of the zero-mean prior on each pose translation, metres."""
    rounds: int = 1
    """Match-and-solve rounds (matches are redrawn with the corrected cameras); one is as
    good as more for errors well within the gate (a few tenths of a degree, a few mm)."""
    iterations: int = 6
    """Reweighted least-squares iterations per round."""
    min_matches: int = 50
    """A camera pair with fewer matches than this contributes nothing."""
    systematic_error_mm: float = 11.0
    """The sensor's systematic depth error at zero distance, mm (Azure Kinect: under 11 mm)."""
    distance_error_fraction: float = 0.001
    """...plus this share of the distance (Azure Kinect: 0.1 %). A correction that moves any
    point its camera sees by more than this budget at that point's distance is refused."""
    min_confirmation: float = 0.5
    """A camera's correction is applied only when, with the corrections solved from one half
    of the overlaps (alternate world cubes), at least this share of the change they predict
    in its overlaps' gaps shows in the other half's (each half in turn, pooled;
    `heldout_confirmation`)."""
    heldout_block_m: float = 0.05
    """Side of the world cubes that alternate between the two halves, metres."""

    def __post_init__(self) -> None:
        if self.sample_step_px < 1 or self.rounds < 1 or self.iterations < 1:
            raise ValueError("align: sample_step_px, rounds and iterations must be >= 1")
        if not (self.gate_m > 0 and self.huber_m > 0 and self.offset_prior_m > 0
                and self.rotation_prior_deg > 0 and self.translation_prior_m > 0):
            raise ValueError("align: gate_m, huber_m and the priors must be > 0")
        if not (self.systematic_error_mm >= 0 and self.distance_error_fraction >= 0
                and self.systematic_error_mm + self.distance_error_fraction > 0):
            raise ValueError("align: the sensor's error budget must be >= 0 and not zero")
        if not self.heldout_block_m > 0:
            raise ValueError("align: heldout_block_m must be > 0")


@dataclass(frozen=True)
class DepthView:
    """One filtered depth image with its camera model and pose."""

    depth_m: NDArray[np.float32]
    """(H, W) metres, 0 = invalid."""
    intrinsics: Intrinsics
    world_from_depth: FloatArray
    """4x4 camera pose, metres."""


@dataclass(frozen=True)
class CameraCorrection:
    """What the alignment decided for one camera."""

    status: str
    """APPLIED, BEYOND_BUDGET, NOT_SUPPORTED, NO_OVERLAP or OFF."""
    matches: int = 0
    """Overlap samples of the camera (with every other camera, both ways)."""
    max_shift_m: float = 0.0
    """Largest move of a point the camera sees under the correction found, metres (also
    for a correction that was not applied)."""
    budget_share: float = 0.0
    """The largest ratio of a point's move to the sensor's budget at its distance (> 1:
    beyond the budget)."""
    confirmation: float | None = None
    """Share of the correction the held-out overlaps show (None: not measured)."""
    proposed: FloatArray = field(default_factory=lambda: np.zeros(7))
    """(7,) the correction found: rotation vector (rad), translation (m), range change (m)."""


@dataclass(frozen=True)
class Corrections:
    """What the alignment found and kept."""

    offsets_m: FloatArray
    """(C,) range offset of each camera, metres: measured range = true range + offset."""
    world_from_depth: FloatArray
    """(C, 4, 4) corrected camera poses."""
    cameras: tuple[CameraCorrection, ...] = ()
    """Per camera, what was decided and why (empty when nothing was estimated)."""
    poses_shown: bool | None = None
    """Whether the held-out overlaps showed the pose touch-ups (`poses_shown`; None: not
    tested, with ``poses`` or ``offsets`` off or nothing to align)."""


def budget_m(range_m: FloatArray, config: AlignConfig) -> FloatArray:
    """The sensor's systematic error budget at each distance, metres."""
    return config.systematic_error_mm * 1e-3 + config.distance_error_fraction * range_m


def budget_shares(cams: list[SampledCamera], poses: FloatArray, x: FloatArray,
                  config: AlignConfig) -> tuple[FloatArray, FloatArray]:
    """(C,) the largest share of the budget a correction uses at any of the camera's
    samples, and (C,) the largest shift, metres."""
    shares, largest = np.zeros(len(cams)), np.zeros(len(cams))
    for k, cam in enumerate(cams):
        if len(cam.points) == 0:
            continue
        moved = shifts_m(cam, poses[k], x[k])
        shares[k] = float(np.max(moved / budget_m(np.linalg.norm(cam.points, axis=1), config)))
        largest[k] = float(moved.max())
    return shares, largest


def _all_matches(cams: list[SampledCamera], poses: FloatArray, offsets: FloatArray,
                 config: AlignConfig) -> dict[tuple[int, int], Matches]:
    matches = {}
    for i in range(len(cams)):
        for j in range(len(cams)):
            if i != j:
                m = pair_matches(cams, poses, offsets, i, j, config)
                if len(m.rhs) >= config.min_matches:
                    matches[(i, j)] = m
    return matches


def _decide(matches: dict[tuple[int, int], Matches], cams: list[SampledCamera],
            poses: FloatArray, applied: FloatArray, config: AlignConfig,
            status: dict[int, CameraCorrection]) -> FloatArray:
    """The round's corrections, refusing (one camera at a time, the worst first) those
    beyond the budget (with what earlier rounds applied, which stays) and those the
    held-out half does not show; ``status`` gets each camera's decision.

    A camera refused as beyond the budget leaves the solve with its overlaps: its depth or
    pose is off by more than the sensor explains, and held as an anchor it would drag its
    neighbours towards its error. A camera whose correction is not shown stays in as an
    anchor, held as captured."""
    count = len(cams)
    while True:
        excluded = {k for k, s in status.items() if s.status == BEYOND_BUDGET}
        active = {pair: m for pair, m in matches.items() if not excluded.intersection(pair)}
        linked = {k for pair in active for k in pair}
        for k in range(count):
            if k not in linked and k not in status:
                status[k] = CameraCorrection(NO_OVERLAP)
        fixed = frozenset(status)
        free = [k for k in range(count) if k not in fixed]
        x = solve(active, count, config, fixed)
        if not free:
            return x
        shares, largest = budget_shares(cams, poses, applied + x, config)
        worst = max(free, key=lambda k: shares[k])
        if shares[worst] > 1.0:
            status[worst] = CameraCorrection(BEYOND_BUDGET, max_shift_m=float(largest[worst]),
                                             budget_share=float(shares[worst]),
                                             proposed=applied[worst] + x[worst])
            continue
        shown = np.nan_to_num(heldout_confirmation(active, count, config, fixed),
                              nan=-np.inf)
        weakest = min(free, key=lambda k: shown[k])
        if shown[weakest] < config.min_confirmation:
            status[weakest] = CameraCorrection(
                NOT_SUPPORTED, max_shift_m=float(largest[weakest]),
                budget_share=float(shares[weakest]), confirmation=_finite(shown[weakest]),
                proposed=applied[weakest] + x[weakest])
            continue
        for k in free:
            status[k] = CameraCorrection(APPLIED, max_shift_m=float(largest[k]),
                                         budget_share=float(shares[k]),
                                         confirmation=_finite(shown[k]),
                                         proposed=applied[k] + x[k])
        return x


def _finite(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None


def _match_counts(matches: dict[tuple[int, int], Matches], count: int) -> list[int]:
    totals = [0] * count
    for (i, j), m in matches.items():
        totals[i] += len(m.rhs)
        totals[j] += len(m.rhs)
    return totals


def estimate_corrections(views: list[DepthView], config: AlignConfig) -> Corrections:
    """Range offsets and corrected poses of the cameras from their overlaps, each within
    the sensor's budget and supported by held-out overlaps (else the camera is kept)."""
    count = len(views)
    poses = np.array([np.asarray(v.world_from_depth, dtype=np.float64) for v in views])
    offsets = np.zeros(count)
    if count < 2 or not (config.offsets or config.poses):
        return Corrections(offsets, poses, tuple(CameraCorrection(OFF) for _ in views))
    cams = [sample_camera(v, config.sample_step_px, config.edge_margin_px) for v in views]
    applied = np.zeros((count, 7))
    refused: dict[int, CameraCorrection] = {}
    counts = [0] * count
    shown: bool | None = None
    for _ in range(config.rounds):
        matches = _all_matches(cams, poses, offsets, config)
        counts = _match_counts(matches, count)
        status: dict[int, CameraCorrection] = dict(refused)
        model = config
        if config.offsets and config.poses:
            shown = poses_shown(matches, count, config, frozenset(refused))
            model = config if shown else replace(config, poses=False)
        x = _decide(matches, cams, poses, applied, model, status)
        refused = {k: s for k, s in status.items() if s.status != APPLIED}
        poses, offsets = apply_correction(poses, offsets, x)
        applied += x
    decided = tuple(_with_matches(status.get(k, CameraCorrection(NO_OVERLAP)), counts[k])
                    for k in range(count))
    return Corrections(offsets, poses, decided, shown)


def _with_matches(found: CameraCorrection, matches: int) -> CameraCorrection:
    return CameraCorrection(found.status, matches, found.max_shift_m, found.budget_share,
                            found.confirmation, found.proposed)


def _pose_change(before: FloatArray, after: FloatArray) -> dict[str, float]:
    turn = (np.trace(before[:3, :3].T @ after[:3, :3]) - 1) / 2
    return {"rotation_deg": round(float(np.degrees(np.arccos(np.clip(turn, -1, 1)))), 4),
            "translation_mm": round(float(np.linalg.norm(after[:3, 3] - before[:3, 3])) * 1e3,
                                    3)}


def _camera_figures(found: CameraCorrection) -> dict[str, object]:
    """One camera's decision and the correction found (applied or not), for the report."""
    shown = found.confirmation
    return {"status": found.status, "matches": found.matches,
            "rotation_deg": round(float(np.degrees(np.linalg.norm(found.proposed[:3]))), 4),
            "translation_mm": round(float(np.linalg.norm(found.proposed[3:6])) * 1e3, 3),
            "range_offset_mm": round(float(-found.proposed[6]) * 1e3, 3),
            "max_shift_mm": round(found.max_shift_m * 1e3, 3),
            "budget_share": round(found.budget_share, 3),
            "confirmation": None if shown is None else round(shown, 3)}


def align_report(camera_ids: list[str], poses_before: FloatArray, found: Corrections,
                 config: AlignConfig) -> dict[str, Any]:
    """The stage's figures: offsets and pose changes applied, each camera's decision with the
    correction found, whether the overlaps showed pose touch-ups, and a warning per
    correction refused as beyond the budget."""
    warnings = [
        f"align: {cid}'s correction refused: it would move what the camera sees by up to "
        f"{c.max_shift_m * 1e3:.1f} mm, {c.budget_share:.1f}x the sensor's error budget "
        f"({config.systematic_error_mm:g} mm + {config.distance_error_fraction * 100:g} % of "
        "the distance); the camera is kept as captured (check the rig's calibration)"
        for cid, c in zip(camera_ids, found.cameras, strict=True) if c.status == BEYOND_BUDGET]
    return {
        "depth_offset_mm": {cid: round(float(o) * 1e3, 3)
                            for cid, o in zip(camera_ids, found.offsets_m, strict=True)},
        "pose_change": {cid: _pose_change(np.asarray(b), a) for cid, b, a
                        in zip(camera_ids, poses_before, found.world_from_depth, strict=True)},
        "cameras": {cid: _camera_figures(c)
                    for cid, c in zip(camera_ids, found.cameras, strict=True)},
        "poses_shown": found.poses_shown,
        "budget": {"systematic_error_mm": config.systematic_error_mm,
                   "distance_error_fraction": config.distance_error_fraction},
        "warnings": warnings,
    }


def apply_offsets(depth_m: NDArray[np.float32], rays: NDArray[np.float32],
                  offset_m: float) -> NDArray[np.float32]:
    """Depth with the camera's range offset removed (invalid pixels stay 0).

    rays: (H, W, 3) from :func:`pipeline.reconstruct.registration.ray_image`; the offset is
    along each ray, so z changes by offset / |ray|.
    """
    corrected = depth_m - np.float32(offset_m) / np.linalg.norm(rays, axis=2)
    return np.where(depth_m > 0, np.maximum(corrected, np.float32(1e-6)),
                    np.float32(0.0)).astype(np.float32)
