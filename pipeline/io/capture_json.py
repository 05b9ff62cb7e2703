"""capture.json to and from :class:`pipeline.capture.CaptureMeta`, with validation.

Every error is a ``ValueError`` whose message names the file and the field at fault.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from pipeline.capture import (
    CAMERA_ID_PATTERN,
    FORMAT_ID,
    BoardSpec,
    CameraInfo,
    CaptureMeta,
    FrameInfo,
    Intrinsics,
    Target,
)

_DISTORTION_MAX = 8
_RIGID_TOLERANCE = 1e-3
ARUCO_DICTIONARIES = frozenset(
    f"DICT_{bits}X{bits}_{n}" for bits in (4, 5, 6, 7) for n in (50, 100, 250, 1000)
) | {"DICT_ARUCO_ORIGINAL", "DICT_APRILTAG_16h5", "DICT_APRILTAG_25h9",
     "DICT_APRILTAG_36h10", "DICT_APRILTAG_36h11", "DICT_ARUCO_MIP_36h12"}
_DICTIONARY_SIZES = {name: int(name.rsplit("_", 1)[1]) for name in ARUCO_DICTIONARIES
                     if name.rsplit("_", 1)[1].isdigit()}


class _Where:
    """Builds 'capture.json: cameras[2].depth_intrinsics.fx' style locations."""

    def __init__(self, path: str) -> None:
        self.path = path

    def error(self, message: str) -> ValueError:
        return ValueError(f"capture.json: {self.path}: {message}" if self.path
                          else f"capture.json: {message}")

    def __truediv__(self, key: str | int) -> _Where:
        if isinstance(key, int):
            return _Where(f"{self.path}[{key}]")
        return _Where(f"{self.path}.{key}" if self.path else key)


def _field(obj: Mapping[str, Any], key: str, where: _Where) -> Any:
    if key not in obj:
        raise (where / key).error("is missing")
    return obj[key]


def _number(value: Any, where: _Where, *, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise where.error(f"must be a number, got {type(value).__name__}")
    if not math.isfinite(value):
        raise where.error(f"must be finite, got {value}")
    if positive and value <= 0:
        raise where.error(f"must be positive, got {value}")
    return float(value)


def _integer(value: Any, where: _Where, *, minimum: int = 0) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise where.error(f"must be an integer, got {value!r}")
    if value < minimum:
        raise where.error(f"must be at least {minimum}, got {value}")
    return value


def _object(value: Any, where: _Where) -> Mapping[str, Any]:
    if not isinstance(value, dict):
        raise where.error(f"must be an object, got {type(value).__name__}")
    return value


def _list(value: Any, where: _Where, *, nonempty: bool = True) -> list[Any]:
    if not isinstance(value, list):
        raise where.error(f"must be a list, got {type(value).__name__}")
    if nonempty and not value:
        raise where.error("must not be empty")
    return value


def parse_rigid(value: Any, where: _Where) -> NDArray[np.float64]:
    """A 4x4 row-major rigid transform: finite, rotation orthonormal with det +1."""
    rows = _list(value, where)
    if len(rows) != 4 or not all(isinstance(r, list) and len(r) == 4 for r in rows):
        raise where.error("must be a 4x4 nested list")
    matrix = np.array([[_number(v, where / i / j) for j, v in enumerate(r)]
                       for i, r in enumerate(rows)])
    if not np.allclose(matrix[3], [0, 0, 0, 1], atol=1e-9):
        raise where.error(f"last row must be [0,0,0,1], got {matrix[3].tolist()}")
    rotation = matrix[:3, :3]
    if (not np.allclose(rotation.T @ rotation, np.eye(3), atol=_RIGID_TOLERANCE)
            or np.linalg.det(rotation) < 0):
        raise where.error("is not rigid (its 3x3 block is not a rotation)")
    return matrix


def parse_intrinsics(value: Any, where: _Where) -> Intrinsics:
    obj = _object(value, where)
    distortion = _list(obj.get("distortion", []), where / "distortion", nonempty=False)
    if len(distortion) > _DISTORTION_MAX:
        raise (where / "distortion").error(f"has {len(distortion)} values, at most 8")
    return Intrinsics(
        width=_integer(_field(obj, "width", where), where / "width", minimum=1),
        height=_integer(_field(obj, "height", where), where / "height", minimum=1),
        fx=_number(_field(obj, "fx", where), where / "fx", positive=True),
        fy=_number(_field(obj, "fy", where), where / "fy", positive=True),
        cx=_number(_field(obj, "cx", where), where / "cx"),
        cy=_number(_field(obj, "cy", where), where / "cy"),
        distortion=tuple(_number(d, where / "distortion" / i) for i, d in enumerate(distortion)),
    )


def _parse_camera(value: Any, where: _Where) -> CameraInfo:
    obj = _object(value, where)
    camera_id = _field(obj, "id", where)
    if not isinstance(camera_id, str) or not re.fullmatch(CAMERA_ID_PATTERN, camera_id):
        raise (where / "id").error(f"{camera_id!r} does not match {CAMERA_ID_PATTERN}")
    color_intrinsics = obj.get("color_intrinsics")
    color_from_depth = obj.get("color_from_depth")
    if (color_intrinsics is None) != (color_from_depth is None):
        raise where.error("color_intrinsics and color_from_depth must both be set or both null")
    world_from_depth = obj.get("world_from_depth")
    return CameraInfo(
        id=camera_id,
        depth_intrinsics=parse_intrinsics(_field(obj, "depth_intrinsics", where),
                                          where / "depth_intrinsics"),
        color_intrinsics=None if color_intrinsics is None
        else parse_intrinsics(color_intrinsics, where / "color_intrinsics"),
        color_from_depth=None if color_from_depth is None
        else parse_rigid(color_from_depth, where / "color_from_depth"),
        world_from_depth=None if world_from_depth is None
        else parse_rigid(world_from_depth, where / "world_from_depth"),
    )


def _parse_board(value: Any, where: _Where) -> BoardSpec:
    obj = _object(value, where)
    dictionary = _field(obj, "dictionary", where)
    if dictionary not in ARUCO_DICTIONARIES:
        raise (where / "dictionary").error(f"unknown ArUco dictionary {dictionary!r}")
    board = BoardSpec(
        dictionary=dictionary,
        squares_x=_integer(_field(obj, "squares_x", where), where / "squares_x", minimum=2),
        squares_y=_integer(_field(obj, "squares_y", where), where / "squares_y", minimum=2),
        square_length_m=_number(_field(obj, "square_length_m", where),
                                where / "square_length_m", positive=True),
        marker_length_m=_number(_field(obj, "marker_length_m", where),
                                where / "marker_length_m", positive=True),
        first_marker_id=_integer(obj.get("first_marker_id", 0), where / "first_marker_id"),
        target_from_board=parse_rigid(obj.get("target_from_board", np.eye(4).tolist()),
                                      where / "target_from_board"),
    )
    if board.marker_length_m >= board.square_length_m:
        raise (where / "marker_length_m").error("must be smaller than square_length_m")
    size = _DICTIONARY_SIZES.get(dictionary)
    if size is not None and board.first_marker_id + marker_count(board) > size:
        last_id = board.first_marker_id + marker_count(board) - 1
        raise where.error(f"needs marker ids up to {last_id} but {dictionary} has {size}")
    return board


def marker_count(board: BoardSpec) -> int:
    """ChArUco boards carry a marker on every other square."""
    return (board.squares_x * board.squares_y) // 2


def _parse_target(value: Any, where: _Where) -> Target | None:
    if value is None:
        return None
    obj = _object(value, where)
    boards = tuple(_parse_board(b, where / "boards" / i)
                   for i, b in enumerate(_list(_field(obj, "boards", where), where / "boards")))
    used: set[int] = set()
    for i, board in enumerate(boards):
        ids = set(range(board.first_marker_id, board.first_marker_id + marker_count(board)))
        if used & ids:
            raise (where / "boards" / i).error("marker ids repeat across boards")
        used |= ids
    return Target(boards=boards)


def _parse_frames(value: Any, where: _Where) -> tuple[FrameInfo, ...]:
    frames = []
    seen: set[int] = set()
    for i, item in enumerate(_list(value, where)):
        obj = _object(item, where / i)
        index = _integer(_field(obj, "index", where / i), where / i / "index")
        if index > 999_999:
            raise (where / i / "index").error("must fit in six digits")
        if index in seen:
            raise (where / i / "index").error(f"frame {index} is listed twice")
        seen.add(index)
        timestamp = _integer(obj.get("timestamp_us", 0), where / i / "timestamp_us")
        frames.append(FrameInfo(index=index, timestamp_us=timestamp))
    return tuple(frames)


def meta_from_json(document: Any) -> CaptureMeta:
    """Validates a parsed capture.json and returns its model."""
    root = _Where("")
    obj = _object(document, root)
    fmt = obj.get("format")
    if fmt != FORMAT_ID:
        raise (root / "format").error(f"unknown format {fmt!r}, expected {FORMAT_ID!r}")
    cameras = tuple(_parse_camera(c, root / "cameras" / i)
                    for i, c in enumerate(_list(_field(obj, "cameras", root), root / "cameras")))
    ids = [c.id for c in cameras]
    duplicates = sorted({i for i in ids if ids.count(i) > 1})
    if duplicates:
        raise (root / "cameras").error(f"camera ids repeat: {', '.join(duplicates)}")
    return CaptureMeta(
        depth_scale=_number(_field(obj, "depth_scale", root), root / "depth_scale", positive=True),
        cameras=cameras,
        frames=_parse_frames(_field(obj, "frames", root), root / "frames"),
        target=_parse_target(obj.get("target"), root / "target"),
    )


def _intrinsics_json(intr: Intrinsics) -> dict[str, Any]:
    return {"width": intr.width, "height": intr.height, "fx": intr.fx, "fy": intr.fy,
            "cx": intr.cx, "cy": intr.cy, "distortion": list(intr.distortion)}


def _matrix_json(matrix: NDArray[np.float64] | None) -> list[list[float]] | None:
    return None if matrix is None else np.asarray(matrix, dtype=float).tolist()


def meta_to_json(meta: CaptureMeta) -> dict[str, Any]:
    """The capture.json document of a capture model."""
    target = None
    if meta.target is not None:
        target = {"boards": [
            {"dictionary": b.dictionary, "squares_x": b.squares_x, "squares_y": b.squares_y,
             "square_length_m": b.square_length_m, "marker_length_m": b.marker_length_m,
             "first_marker_id": b.first_marker_id,
             "target_from_board": _matrix_json(b.target_from_board)}
            for b in meta.target.boards]}
    return {
        "format": FORMAT_ID,
        "depth_scale": meta.depth_scale,
        "cameras": [
            {"id": c.id,
             "depth_intrinsics": _intrinsics_json(c.depth_intrinsics),
             "color_intrinsics": None if c.color_intrinsics is None
             else _intrinsics_json(c.color_intrinsics),
             "color_from_depth": _matrix_json(c.color_from_depth),
             "world_from_depth": _matrix_json(c.world_from_depth)}
            for c in meta.cameras],
        "frames": [{"index": f.index, "timestamp_us": f.timestamp_us} for f in meta.frames],
        "target": target,
    }
