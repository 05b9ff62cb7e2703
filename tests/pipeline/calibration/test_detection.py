"""ChArUco detection on photograph-like images: perspective, blur, noise, uneven light, JPEG
and lens distortion; several boards in one image; bad boards and images refused by name."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from pipeline.calibration.detection import (
    TargetDetector,
    charuco_board,
    target_geometry,
    undistort_pixels,
)
from pipeline.calibration.transforms import from_rotvec
from pipeline.capture import BoardSpec, Intrinsics, Target

BOARD = BoardSpec("DICT_5X5_100", 9, 6, 0.06, 0.045, 0)
INTRINSICS = Intrinsics(1600, 1200, 1400.0, 1400.0, 801.3, 597.8, (-0.12, 0.05, 0.0004, -0.0002))
PX_PER_M = 3000.0
SUPERSAMPLE = 3


def _paper(specs: list[BoardSpec], border: int) -> np.ndarray:
    """White paper with the boards printed where their target_from_board (x, y shift) says."""
    sizes = [(int(b.squares_x * b.square_length_m * PX_PER_M),
              int(b.squares_y * b.square_length_m * PX_PER_M)) for b in specs]
    origins = [(int(round(b.target_from_board[0, 3] * PX_PER_M)),
                int(round(b.target_from_board[1, 3] * PX_PER_M))) for b in specs]
    width = max(o[0] + s[0] for o, s in zip(origins, sizes, strict=True)) + 2 * border
    height = max(o[1] + s[1] for o, s in zip(origins, sizes, strict=True)) + 2 * border
    paper = np.full((height, width), 255.0, np.float32)
    for spec, (x, y), (w, h) in zip(specs, origins, sizes, strict=True):
        paper[border + y:border + y + h, border + x:border + x + w] = \
            charuco_board(spec).generateImage((w, h), marginSize=0)
    return paper


def _photograph(specs: list[BoardSpec], camera_from_board: np.ndarray, seed: int,
                distorted: bool = True) -> np.ndarray:
    """Boards 'photographed': printed on white paper, seen in perspective through a lens with
    distortion, under a lighting gradient, slightly out of focus, noisy, JPEG-compressed."""
    rng = np.random.default_rng(seed)
    border = 150
    paper = _paper(specs, border)
    s = 1.0 / PX_PER_M
    paper_to_board = np.array([[s, 0, (0.5 - border) * s], [0, s, (0.5 - border) * s], [0, 0, 1]])
    k = INTRINSICS.matrix()
    # Optics integrate over each pixel: render finer, then average blocks of pixels.
    n = SUPERSAMPLE
    fine = np.array([[n, 0, (n - 1) / 2], [0, n, (n - 1) / 2], [0, 0, 1]])
    homography = fine @ k @ camera_from_board[:3, [0, 1, 3]] @ paper_to_board
    size = (INTRINSICS.width, INTRINSICS.height)
    ideal = cv2.resize(cv2.warpPerspective(paper, homography, (size[0] * n, size[1] * n),
                                           flags=cv2.INTER_CUBIC, borderValue=60.0),
                       size, interpolation=cv2.INTER_AREA)
    image = ideal
    if distorted:
        grid = np.stack(np.meshgrid(np.arange(size[0], dtype=np.float64),
                                    np.arange(size[1], dtype=np.float64)), -1).reshape(-1, 1, 2)
        source = cv2.undistortPoints(grid, k, INTRINSICS.distortion_coeffs(), P=k)
        source = source.reshape(size[1], size[0], 2).astype(np.float32)
        image = cv2.remap(ideal, source[..., 0], source[..., 1], cv2.INTER_CUBIC)
    ys, xs = np.mgrid[0:size[1], 0:size[0]]
    light = 0.45 + 0.5 * (xs / size[0]) * (0.7 + 0.3 * ys / size[1])
    image = cv2.GaussianBlur(image * light, (0, 0), 0.9) + rng.normal(0, 3.0, image.shape)
    gray = np.clip(image, 0, 255).astype(np.uint8)
    ok, jpeg = cv2.imencode(".jpg", gray, [cv2.IMWRITE_JPEG_QUALITY, 92])
    assert ok
    decoded = np.asarray(cv2.imdecode(jpeg, cv2.IMREAD_GRAYSCALE))
    return np.repeat(decoded[:, :, None], 3, axis=2)


def _truth(points_board: np.ndarray, camera_from_board: np.ndarray) -> np.ndarray:
    cam = points_board @ camera_from_board[:3, :3].T + camera_from_board[:3, 3]
    pixels = cam @ INTRINSICS.matrix().T
    return pixels[:, :2] / pixels[:, 2:3]


@pytest.mark.parametrize("seed,rotvec,distance_m", [
    (0, (0.5, -0.3, 0.1), 1.4), (1, (-0.2, 0.7, -0.3), 1.8), (2, (0.9, 0.1, 2.0), 1.2)])
def test_corners_of_a_photographed_board_within_a_tenth_of_a_pixel(
        seed: int, rotvec: tuple[float, float, float], distance_m: float) -> None:
    geometry = target_geometry(Target(boards=(BOARD,)))
    centre = np.array([BOARD.squares_x, BOARD.squares_y, 0.0]) * BOARD.square_length_m / 2
    rotation = from_rotvec(np.array(rotvec), np.zeros(3))[:3, :3]
    camera_from_board = from_rotvec(np.array(rotvec), np.array([0.0, 0.0, distance_m])
                                    - rotation @ centre)
    image = _photograph([BOARD], camera_from_board, seed)
    ids, pixels = TargetDetector(geometry).detect(image, INTRINSICS)
    assert len(ids) >= 0.9 * len(geometry.points_target)
    assert len(set(ids.tolist())) == len(ids)
    errors = np.linalg.norm(undistort_pixels(pixels, INTRINSICS)
                            - _truth(geometry.points_target[ids], camera_from_board), axis=1)
    assert np.sqrt(np.mean(errors**2)) < 0.1
    assert errors.max() < 0.4


def test_two_boards_in_one_image_keep_their_own_ids() -> None:
    second = BoardSpec("DICT_5X5_100", 5, 4, 0.06, 0.045, 30,
                       target_from_board=from_rotvec(np.zeros(3), np.array([0.62, 0.0, 0.0])))
    first = BoardSpec("DICT_5X5_100", 9, 6, 0.06, 0.045, 0)
    geometry = target_geometry(Target(boards=(first, second)))
    camera_from_board = from_rotvec(np.array([0.1, -0.2, 0.0]), np.array([-0.5, -0.2, 1.6]))
    image = _photograph([first, second], camera_from_board, 3, distorted=False)
    ids, pixels = TargetDetector(geometry).detect(image)
    from_second = ids >= geometry.first_point[1]
    assert from_second.sum() >= 10 and (~from_second).sum() >= 30
    errors = np.linalg.norm(pixels - _truth(geometry.points_target[ids], camera_from_board),
                            axis=1)
    assert np.median(errors) < 0.15


def test_image_without_target_gives_no_corners() -> None:
    geometry = target_geometry(Target(boards=(BOARD,)))
    noise = np.random.default_rng(0).integers(0, 255, (480, 640, 3), dtype=np.uint8)
    ids, pixels = TargetDetector(geometry).detect(noise)
    assert len(ids) == 0 and pixels.shape == (0, 2)


def test_unknown_dictionary_and_missing_target_are_named() -> None:
    with pytest.raises(ValueError, match="unknown ArUco dictionary 'DICT_9X9_7'"):
        target_geometry(Target(boards=(BoardSpec("DICT_9X9_7", 5, 4, 0.06, 0.045, 0),)))
    with pytest.raises(ValueError, match="target is null"):
        target_geometry(None)
    with pytest.raises(ValueError, match="marker ids up to"):
        target_geometry(Target(boards=(BoardSpec("DICT_4X4_50", 9, 9, 0.06, 0.045, 20),)))


def test_bad_image_is_refused() -> None:
    detector = TargetDetector(target_geometry(Target(boards=(BOARD,))))
    with pytest.raises(ValueError, match="colour image must be"):
        detector.detect(np.zeros((10, 10), np.uint8))
