"""The board-aware corner fit never fails on odd corner sets and moves a corner only a little."""

from __future__ import annotations

import cv2
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.calibration.detection import charuco_board
from pipeline.calibration.subpixel import BoardLayout, gradients, refine_corners
from pipeline.capture import BoardSpec

BOARD = charuco_board(BoardSpec("DICT_5X5_100", 8, 6, 0.08, 0.06, 0))
LAYOUT = BoardLayout.of(BOARD)
IMAGE = cv2.resize(BOARD.generateImage((640, 480)), (320, 240), interpolation=cv2.INTER_AREA)
GRAD = gradients(IMAGE)


def test_layout_matches_the_board() -> None:
    assert LAYOUT.marker_squares.shape == (6, 8) and LAYOUT.marker_squares.sum() == 24
    assert not LAYOUT.marker_squares[0, 0] and LAYOUT.marker_squares[0, 1]
    np.testing.assert_allclose(LAYOUT.corner_squares[0], [1.0, 1.0])
    assert abs(LAYOUT.margin_squares - 0.125) < 1e-6


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(0, 34), min_size=0, max_size=35, unique=True),
       st.floats(-300, 700), st.floats(0.1, 80), st.floats(-3, 3))
def test_any_corner_set_is_handled(ids: list[int], offset: float, scale: float,
                                   jitter: float) -> None:
    corner_ids = np.array(ids, dtype=np.int64)
    pixels = LAYOUT.corner_squares[corner_ids] * scale + offset + jitter
    refined = refine_corners(GRAD, corner_ids, pixels, LAYOUT)
    assert refined.shape == (len(ids), 2)
    assert np.all(np.isfinite(refined))
    # A corner moves at most a fraction of a square from where it was found.
    assert np.all(np.linalg.norm(refined - pixels, axis=1) <= 0.15 * scale * 1.5 + 1e-9)


def test_exact_corners_of_a_rendered_board() -> None:
    ids = np.arange(35)
    truth = LAYOUT.corner_squares[ids] * 40.0 - 0.5  # 40 px squares; pixel centres at .0
    start = truth + np.random.default_rng(0).normal(0, 0.3, truth.shape)
    refined = refine_corners(GRAD, ids, start, LAYOUT)
    assert np.sqrt(np.mean(np.sum((refined - truth) ** 2, axis=1))) < 0.05
