"""ChArUco corner detection in colour images, with sub-pixel refinement.

Every ChArUco corner of every board of a target gets one *point id*; its position in the
target frame is ``TargetGeometry.points_target[point_id]``. Detected pixels are undistorted
once, so everything downstream works with a plain pinhole model.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from pipeline.calibration.subpixel import BoardLayout, gradients, refine_corners
from pipeline.calibration.transforms import transform_points
from pipeline.capture import BoardSpec, Intrinsics, Target

_MIN_BOARD_CORNERS = 6
"""Fewer corners of one board than this cannot be checked against each other: dropped."""
_HOMOGRAPHY_TOLERANCE_PX = 1.5
"""Corners further than this from the board's homography through the others are dropped."""


@dataclass(frozen=True)
class ViewCorners:
    """The target corners one colour camera saw at one frame."""

    camera_id: str
    frame_index: int
    point_ids: NDArray[np.int64]
    """(N,) ids into TargetGeometry.points_target."""
    pixels: NDArray[np.float64]
    """(N, 2) undistorted pixel positions (pinhole model of the colour intrinsics)."""


@dataclass(frozen=True)
class TargetGeometry:
    """Where every ChArUco corner of a target lies, and the OpenCV boards to find them."""

    points_target: NDArray[np.float64]
    """(M, 3) corner positions in the target frame, metres."""
    board_of_point: NDArray[np.int64]
    """(M,) index of the board each corner belongs to."""
    boards: tuple[cv2.aruco.CharucoBoard, ...]
    dictionaries: tuple[str, ...]
    """ArUco dictionary name of each board."""
    first_point: tuple[int, ...]
    """Point id of each board's ChArUco corner 0."""

    @property
    def is_planar(self) -> bool:
        """True when all corners lie on one plane (a single flat board)."""
        centred = self.points_target - self.points_target.mean(axis=0)
        return bool(np.linalg.svd(centred, compute_uv=False)[2] < 1e-6)


def aruco_dictionary(name: str) -> cv2.aruco.Dictionary:
    """OpenCV's predefined dictionary of that name (ValueError when there is none)."""
    code = getattr(cv2.aruco, name, None) if name.startswith("DICT_") else None
    if not isinstance(code, int):
        raise ValueError(f"target: unknown ArUco dictionary {name!r}")
    return cv2.aruco.getPredefinedDictionary(code)


def charuco_board(spec: BoardSpec) -> cv2.aruco.CharucoBoard:
    """The OpenCV board of a spec, its markers numbered from ``first_marker_id``."""
    dictionary = aruco_dictionary(spec.dictionary)
    count = (spec.squares_x * spec.squares_y) // 2
    ids = np.arange(spec.first_marker_id, spec.first_marker_id + count, dtype=np.int32)
    if ids[-1] >= dictionary.bytesList.shape[0]:
        raise ValueError(f"target: board needs marker ids up to {ids[-1]} but "
                         f"{spec.dictionary} has {dictionary.bytesList.shape[0]}")
    return cv2.aruco.CharucoBoard((spec.squares_x, spec.squares_y), spec.square_length_m,
                                  spec.marker_length_m, dictionary, ids)


def target_geometry(target: Target | None) -> TargetGeometry:
    """All corners of all boards of a target, in the target frame."""
    if target is None or not target.boards:
        raise ValueError("capture.json: target is null: a calibration capture must describe its "
                         "ChArUco target")
    boards, points, owner, first = [], [], [], []
    count = 0
    for index, spec in enumerate(target.boards):
        board = charuco_board(spec)
        corners_board = np.asarray(board.getChessboardCorners(), dtype=float)
        boards.append(board)
        points.append(transform_points(np.asarray(spec.target_from_board, float), corners_board))
        owner.append(np.full(len(corners_board), index, dtype=np.int64))
        first.append(count)
        count += len(corners_board)
    return TargetGeometry(points_target=np.concatenate(points),
                          board_of_point=np.concatenate(owner), boards=tuple(boards),
                          dictionaries=tuple(s.dictionary for s in target.boards),
                          first_point=tuple(first))


class TargetDetector:
    """Finds a target's ChArUco corners in images; one instance per thread (OpenCV state)."""

    def __init__(self, geometry: TargetGeometry) -> None:
        self.geometry = geometry
        self._layouts = [BoardLayout.of(b) for b in geometry.boards]
        self._marker_detectors = {name: cv2.aruco.ArucoDetector(aruco_dictionary(name))
                                  for name in sorted(set(geometry.dictionaries))}
        self._board_detectors = [cv2.aruco.CharucoDetector(b) for b in geometry.boards]

    def detect(self, image_rgb: NDArray[np.uint8], intrinsics: Intrinsics | None = None
               ) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """Point ids (N,) and distorted pixel positions (N, 2) of the corners in an image.

        intrinsics: the image's camera model; its lens distortion, if any, is taken into
        account by the sub-pixel refinement (None: no distortion).
        """
        if image_rgb.ndim != 3 or image_rgb.shape[2] != 3 or image_rgb.dtype != np.uint8:
            raise ValueError(f"colour image must be (H, W, 3) uint8, got {image_rgb.shape} "
                             f"{image_rgb.dtype}")
        gray = np.asarray(cv2.cvtColor(image_rgb, cv2.COLOR_RGB2GRAY), np.uint8)
        markers = {name: det.detectMarkers(gray)[:2] for name, det in
                   self._marker_detectors.items()}
        all_ids, all_pixels = [], []
        grad = None
        to_ideal = None
        if intrinsics is not None and intrinsics.has_distortion:
            model = intrinsics
            to_ideal = lambda p: undistort_pixels(p, model)  # noqa: E731
        for index, board in enumerate(self.geometry.boards):
            corners, ids = markers[self.geometry.dictionaries[index]]
            if ids is None:
                continue
            board_ids = np.asarray(board.getIds()).ravel()
            mine = np.isin(ids.ravel(), board_ids)
            if mine.sum() < 2:  # ChArUco interpolation needs two markers
                continue
            charuco_corners, charuco_ids, _, _ = self._board_detectors[index].detectBoard(
                gray, markerCorners=[c for c, m in zip(corners, mine, strict=True) if m],
                markerIds=ids[mine])
            if charuco_ids is None or len(charuco_ids) == 0:
                continue
            board_ids_found = charuco_ids.ravel().astype(np.int64)
            if grad is None:
                grad = gradients(gray)
            pixels = refine_corners(grad, board_ids_found,
                                    np.asarray(charuco_corners, np.float64).reshape(-1, 2),
                                    self._layouts[index], to_ideal)
            keep = _plane_consistent(self._layouts[index].corner_squares[board_ids_found],
                                     pixels if to_ideal is None else to_ideal(pixels))
            all_ids.append(board_ids_found[keep] + self.geometry.first_point[index])
            all_pixels.append(pixels[keep])
        if not all_ids:
            return np.zeros(0, dtype=np.int64), np.zeros((0, 2))
        return np.concatenate(all_ids), np.concatenate(all_pixels)


def _plane_consistent(grid: NDArray[np.float64], ideal: NDArray[np.float64]
                      ) -> NDArray[np.bool_]:
    """Corners of one board that a single homography explains (undistorted pixels).

    A board seen at a grazing angle with few markers found sometimes gets corners
    interpolated at the wrong squares; a flat board's corners must agree with one homography,
    and too few corners to check that are not trusted at all.
    """
    keep = np.zeros(len(grid), dtype=bool)
    if len(grid) < _MIN_BOARD_CORNERS:
        return keep
    if np.linalg.svd(grid - grid.mean(axis=0), compute_uv=False)[1] < 0.5:
        return keep  # corners along one line of the board: nothing to check them with
    try:
        homography, inliers = cv2.findHomography(grid, ideal, cv2.RANSAC,
                                                 _HOMOGRAPHY_TOLERANCE_PX)
    except cv2.error:
        return keep
    if homography is None or inliers is None:
        return keep
    keep = np.asarray(inliers, dtype=bool).ravel()
    if keep.sum() < _MIN_BOARD_CORNERS:
        keep[:] = False
    return keep


def undistort_pixels(pixels: NDArray[np.float64], intrinsics: Intrinsics) -> NDArray[np.float64]:
    """(N, 2) distorted pixels to the pixels an ideal pinhole camera with the same K sees."""
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    if not intrinsics.has_distortion or len(pixels) == 0:
        return pixels.copy()
    matrix = intrinsics.matrix()
    out = cv2.undistortPoints(pixels.reshape(-1, 1, 2), matrix, intrinsics.distortion_coeffs(),
                              P=matrix, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS,
                                                  50, 1e-10))
    return np.asarray(out, np.float64).reshape(-1, 2)
