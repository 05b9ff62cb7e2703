"""Sub-pixel ChArUco corners: a Förstner corner fit over the board's own edges.

OpenCV's ``cornerSubPix`` must keep its window inside the thin white margin around the markers,
so it sees a few pixels only and locks onto the pixel grid (errors ~0.1 px, correlated over a
board). Knowing the board, we can do better: a homography from the detected corners tells which
pixels near each corner lie on the chessboard edges through it, and which belong to a marker;
the corner is the point closest, in the least-squares sense, to the edge lines of all the kept
pixels (each pixel's line passes through it orthogonal to its gradient). Windows then reach
most of a square, and the many sub-pixel phases along the edges average the locking out.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

Pixels = NDArray[np.float64]
_EXTENT_SQUARES = 0.7
"""How far along its edges a corner's window reaches (the next corner is 1 square away)."""
_BAND_SIGMAS = 2.0
"""Pixels within this many edge-blur sigmas of a marker are left out (their gradients leak)."""
_MIN_BAND_PX = 1.5
_MAX_HALF_PX = 24
_MAX_SHIFT_SQUARES = 0.15


@dataclass(frozen=True)
class BoardLayout:
    """Where the corners and markers of one ChArUco board are, in units of squares."""

    corner_squares: NDArray[np.float64]
    """(K, 2) position of ChArUco corner k, squares from the board's top-left."""
    marker_squares: NDArray[np.bool_]
    """(squares_y, squares_x) True where a square carries a marker."""
    margin_squares: float
    """White margin between a marker and its square's edge, squares."""

    @classmethod
    def of(cls, board: cv2.aruco.CharucoBoard) -> BoardLayout:
        square = board.getSquareLength()
        columns, rows = board.getChessboardSize()
        has_marker = np.zeros((rows, columns), dtype=bool)
        for corners in board.getObjPoints():
            x, y = (np.asarray(corners)[:, :2].mean(axis=0) / square).astype(int)
            has_marker[y, x] = True
        return cls(corner_squares=np.asarray(board.getChessboardCorners())[:, :2] / square,
                   marker_squares=has_marker,
                   margin_squares=(1.0 - board.getMarkerLength() / square) / 2)


@dataclass(frozen=True)
class Gradients:
    """A grey image and its gradients, grey levels per pixel (Sobel, 3x3)."""

    gray: NDArray[np.float32]
    gx: NDArray[np.float32]
    gy: NDArray[np.float32]


def gradients(gray: NDArray[np.uint8]) -> Gradients:
    """The gradients of a grey image."""
    image = gray.astype(np.float32)
    return Gradients(
        image, np.asarray(cv2.Sobel(image, cv2.CV_32F, 1, 0, ksize=3, scale=0.125), np.float32),
        np.asarray(cv2.Sobel(image, cv2.CV_32F, 0, 1, ksize=3, scale=0.125), np.float32))


def edge_sigma_px(grad: Gradients, windows: list[tuple[int, int, NDArray[np.int64],
                                                              NDArray[np.int64]] | None]) -> float:
    """Blur of the board's edges, pixels: a step of height A blurred by a Gaussian of sigma s
    has a steepest slope of A / (s sqrt(2 pi))."""
    sigmas = []
    for window in windows:
        if window is None:
            continue
        values = grad.gray[window[3], window[2]]
        slope = np.hypot(grad.gx[window[3], window[2]], grad.gy[window[3], window[2]])
        step = float(np.percentile(values, 95) - np.percentile(values, 5))
        steepest = float(np.percentile(slope, 99))
        if steepest > 0:
            sigmas.append(step / (np.sqrt(2 * np.pi) * steepest))
    return float(np.median(sigmas)) if sigmas else 1.0


def _windows(centres: Pixels, halves: NDArray[np.int64], shape: tuple[int, int]
             ) -> list[tuple[int, int, NDArray[np.int64], NDArray[np.int64]] | None]:
    out: list[tuple[int, int, NDArray[np.int64], NDArray[np.int64]] | None] = []
    height, width = shape
    for (x, y), half in zip(np.rint(centres).astype(int), halves, strict=True):
        if x - half < 1 or y - half < 1 or x + half >= width - 1 or y + half >= height - 1:
            out.append(None)
            continue
        ys, xs = np.mgrid[y - half:y + half + 1, x - half:x + half + 1]
        out.append((x - half, y - half, xs.ravel(), ys.ravel()))
    return out


def _edge_pixels(board_xy: Pixels, corner: Pixels, layout: BoardLayout, band_squares: float
                 ) -> NDArray[np.bool_]:
    """Window pixels on the chessboard edges through ``corner`` and clear of any marker."""
    rel = board_xy - corner
    near = np.all(np.abs(rel) < _EXTENT_SQUARES, axis=1)
    square = np.floor(board_xy).astype(int)
    frac = board_xy - square
    rows, columns = layout.marker_squares.shape
    inside = (square[:, 0] >= 0) & (square[:, 0] < columns) & (square[:, 1] >= 0) \
        & (square[:, 1] < rows)
    marked = np.zeros(len(board_xy), dtype=bool)
    marked[inside] = layout.marker_squares[square[inside, 1], square[inside, 0]]
    low, high = layout.margin_squares - band_squares, 1.0 - layout.margin_squares + band_squares
    on_marker = marked & np.all((frac > low) & (frac < high), axis=1)
    return near & ~on_marker


def _forstner(gx: NDArray[np.float32], gy: NDArray[np.float32], xs: NDArray[np.int64],
              ys: NDArray[np.int64]) -> Pixels | None:
    """The point nearest to every pixel's edge line (through it, orthogonal to its gradient)."""
    a, b = gx[ys, xs].astype(np.float64), gy[ys, xs].astype(np.float64)
    aa, ab, bb = a * a, a * b, b * b
    normal = np.array([[aa.sum(), ab.sum()], [ab.sum(), bb.sum()]])
    if np.linalg.cond(normal) > 1e4:  # edges of one direction only: no corner to find
        return None
    rhs = np.array([(aa * xs + ab * ys).sum(), (ab * xs + bb * ys).sum()])
    return np.linalg.solve(normal, rhs)


def _homography(grid: Pixels, pixels: Pixels) -> Pixels | None:
    """Least-squares board-to-image homography, None when the corners cannot fix one."""
    spread = np.linalg.svd(grid - grid.mean(axis=0), compute_uv=False)
    if len(grid) < 4 or spread[1] < 0.5:  # all corners on one line of the board
        return None
    try:
        homography, _ = cv2.findHomography(grid, pixels, 0)
    except cv2.error:
        return None
    if homography is None or not np.all(np.isfinite(homography)) \
            or np.linalg.cond(homography) > 1e12:
        return None
    return np.asarray(homography, np.float64)


def refine_corners(grad: Gradients,
                   corner_ids: NDArray[np.int64], pixels: Pixels, layout: BoardLayout,
                   to_ideal: Callable[[Pixels], Pixels] | None = None, passes: int = 2
                   ) -> Pixels:
    """Refined (N, 2) pixel positions of one board's detected corners.

    to_ideal maps distorted pixels to pinhole pixels (None: no lens distortion); the board
    homography lives there. Corners whose fit fails or jumps far keep their input position.
    """
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    if len(pixels) < 4:
        return pixels.copy()
    ideal = to_ideal or (lambda p: p)
    grid = layout.corner_squares[corner_ids]
    current = pixels.copy()
    for _ in range(passes):
        homography = _homography(grid, ideal(current))
        if homography is None:
            return current
        inverse = np.linalg.inv(homography)
        # Local square size in pixels, from the homography's images of the four neighbours.
        steps = np.array([[1, 0], [0, 1], [-1, 0], [0, -1]], dtype=float)
        around = cv2.perspectiveTransform((grid[:, None, :] + steps[None]).reshape(-1, 1, 2),
                                          homography).reshape(len(grid), 4, 2)
        square_px = np.linalg.norm(around - ideal(current)[:, None], axis=2)
        halves = np.clip(np.ceil(_EXTENT_SQUARES * square_px.max(axis=1)), 2, _MAX_HALF_PX)
        windows = _windows(current, halves.astype(np.int64), grad.gray.shape)
        band_px = max(_MIN_BAND_PX, _BAND_SIGMAS * edge_sigma_px(grad, windows))
        coords = [np.column_stack([w[2], w[3]]).astype(np.float64) for w in windows if w]
        if not coords:
            return current
        board_xy = np.asarray(cv2.perspectiveTransform(
            ideal(np.concatenate(coords)).reshape(-1, 1, 2), inverse), np.float64).reshape(-1, 2)
        offset = 0
        refined = current.copy()
        for k, window in enumerate(windows):
            if window is None:
                continue
            count = len(window[2])
            band = band_px / max(float(square_px[k].min()), 1.0)
            keep = _edge_pixels(board_xy[offset:offset + count], grid[k], layout, band)
            offset += count
            found = _forstner(grad.gx, grad.gy, window[2][keep], window[3][keep])
            if found is not None and (np.linalg.norm(found - pixels[k])
                                      < _MAX_SHIFT_SQUARES * square_px[k].min()):
                refined[k] = found
        current = refined
    return current
