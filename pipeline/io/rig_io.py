"""rig.json: the camera poses a calibration found, with its quality report.

```
{"format": "volumesh.rig/1",
 "world_from_depth": {"cam0": [[...4x4...]], ...},
 "reprojection_rms_px": {...}, "triangulation_error_mm": {...}, "views_used": {...},
 "warnings": [...], ...}
```
Everything besides ``format`` and ``world_from_depth`` is the report, kept at the top level.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from pipeline.capture import CAMERA_ID_PATTERN

RIG_FORMAT_ID = "volumesh.rig/1"


def _plain(value: Any) -> Any:
    """JSON-ready copy: numpy to Python, non-finite floats to null."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _rigid(value: Any, where: str) -> NDArray[np.float64]:
    """A 4x4 rigid transform from nested lists, or ValueError naming ``where``."""
    try:
        matrix = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: must be a 4x4 nested list of numbers") from None
    if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
        raise ValueError(f"{where}: must be a 4x4 nested list of finite numbers")
    if not np.allclose(matrix[3], [0, 0, 0, 1], atol=1e-9):
        raise ValueError(f"{where}: last row must be [0,0,0,1]")
    rotation = matrix[:3, :3]
    if not np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-3) or np.linalg.det(rotation) < 0:
        raise ValueError(f"{where}: is not rigid (its 3x3 block is not a rotation)")
    return matrix


def rig_to_json(world_from_depth: Mapping[str, NDArray[np.float64]],
                report: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The rig.json document of poses (camera id -> 4x4) and a report."""
    extra = {k: v for k, v in (report or {}).items() if k not in ("format", "world_from_depth")}
    return {"format": RIG_FORMAT_ID,
            "world_from_depth": {c: np.asarray(m, dtype=float).tolist()
                                 for c, m in world_from_depth.items()},
            **_plain(extra)}


def rig_from_json(document: Any, name: str = "rig.json"
                  ) -> tuple[dict[str, NDArray[np.float64]], dict[str, Any]]:
    """(world_from_depth per camera, the rest of the document); ValueError naming the field."""
    if not isinstance(document, dict):
        raise ValueError(f"{name}: must be a JSON object")
    fmt = document.get("format", RIG_FORMAT_ID)
    if fmt != RIG_FORMAT_ID:
        raise ValueError(f"{name}: format: unknown format {fmt!r}, expected {RIG_FORMAT_ID!r}")
    poses = document.get("world_from_depth")
    if not isinstance(poses, dict) or not poses:
        raise ValueError(f"{name}: world_from_depth: must be a non-empty object of camera id "
                         "to 4x4 transform")
    out = {}
    for camera_id, matrix in poses.items():
        if not re.fullmatch(CAMERA_ID_PATTERN, camera_id):
            raise ValueError(f"{name}: world_from_depth: camera id {camera_id!r} does not match "
                             f"{CAMERA_ID_PATTERN}")
        out[camera_id] = _rigid(matrix, f"{name}: world_from_depth.{camera_id}")
    return out, {k: v for k, v in document.items() if k not in ("format", "world_from_depth")}


def write_rig(path: str | Path, world_from_depth: Mapping[str, NDArray[np.float64]],
              report: Mapping[str, Any] | None = None) -> None:
    """Writes rig.json (pretty-printed)."""
    Path(path).write_text(json.dumps(rig_to_json(world_from_depth, report), indent=1))


def read_rig(path: str | Path) -> tuple[dict[str, NDArray[np.float64]], dict[str, Any]]:
    """Reads and validates rig.json: (world_from_depth per camera, report)."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ValueError(f"{path}: cannot read rig file ({exc.strerror})") from None
    try:
        document = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path.name}: not valid JSON ({exc})") from None
    return rig_from_json(document, path.name)
