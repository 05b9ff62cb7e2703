"""Camera poses in request bodies: 4x4 rigid transforms checked at the gateway, so a bad rig
is refused at once with a 422 naming the camera (the pipeline checks them again with numpy;
the gateway never imports it)."""

from __future__ import annotations

import math
import re

CAMERA_ID_PATTERN = r"[A-Za-z0-9_-]{1,32}"  # as pipeline.capture (not imported here)


Matrix4 = list[list[float]]


def check_rigid(matrix: Matrix4, where: str) -> Matrix4:
    """The matrix if it is a finite 4x4 rigid transform, else ValueError naming ``where``.

    The pipeline checks poses again with numpy; the gateway keeps its own few lines so that it
    never imports the pipeline, and a bad rig is refused at once with a 422."""
    if len(matrix) != 4 or any(len(row) != 4 for row in matrix):
        raise ValueError(f"{where}: must be a 4x4 nested list")
    if not all(math.isfinite(x) for row in matrix for x in row):
        raise ValueError(f"{where}: must hold finite numbers")
    if any(abs(x - y) > 1e-9 for x, y in zip(matrix[3], (0, 0, 0, 1), strict=True)):
        raise ValueError(f"{where}: last row must be [0,0,0,1]")
    rows = [row[:3] for row in matrix[:3]]
    columns = list(zip(*rows, strict=True))
    for i in range(3):
        for j in range(3):
            dot = sum(a * b for a, b in zip(columns[i], columns[j], strict=True))
            if abs(dot - (1.0 if i == j else 0.0)) > 1e-3:
                raise ValueError(f"{where}: is not rigid (its 3x3 block is not a rotation)")
    (a, b, c), (d, e, f), (g, h, i_) = rows
    if a * (e * i_ - f * h) - b * (d * i_ - f * g) + c * (d * h - e * g) < 0:
        raise ValueError(f"{where}: is a reflection, not a rotation")
    return matrix


def check_poses(poses: dict[str, Matrix4] | None, name: str) -> dict[str, Matrix4] | None:
    for camera_id, matrix in (poses or {}).items():
        if not re.fullmatch(CAMERA_ID_PATTERN, camera_id):
            raise ValueError(f"{name}: camera id {camera_id!r} does not match "
                             f"{CAMERA_ID_PATTERN}")
        check_rigid(matrix, f"{name}.{camera_id}")
    return poses
