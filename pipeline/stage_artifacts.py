"""What the stages share: the artifacts they pass (dicts of numpy arrays), the capture reader
they need, and the mesh and figures read back from merged artifacts."""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from numpy.typing import NDArray

from pipeline.capture import CaptureMeta, View
from pipeline.geometry.mesh import TriangleMesh

if TYPE_CHECKING:
    from pipeline.enhance.networks import EnhanceNetworks

Progress = Callable[[float], None]
Artifacts = dict[str, NDArray[Any]]
NetworksSource = Callable[[], "EnhanceNetworks"]
"""Gives the enhance stage's networks when it needs them: a worker's kept set, loaded only
for a mesh that is enhanced (`WorkerContext.enhance_networks`)."""


class CaptureReader(Protocol):
    """What the stages need of :class:`pipeline.io.capture_io.CaptureReader`."""

    @property
    def meta(self) -> CaptureMeta: ...

    def read_view(self, camera_id: str, frame_index: int, *, with_color: bool = True
                  ) -> View: ...


def require_keys(inputs: Mapping[str, NDArray[Any]], keys: tuple[str, ...], stage: str
                 ) -> list[NDArray[Any]]:
    """The artifacts under ``keys``; ValueError naming the first one missing."""
    missing = [k for k in keys if k not in inputs]
    if missing:
        raise ValueError(f"inputs: stage {stage} needs artifact {missing[0]!r}")
    return [inputs[k] for k in keys]


def stats_artifact(stage: str, figures: Mapping[str, Any]) -> Artifacts:
    """The stage's figures as its ``stats_<stage>`` artifact (a 0-d JSON string array)."""
    return {f"stats_{stage}": np.array(json.dumps(figures, default=float))}


def tick(progress: Progress | None, fraction: float) -> None:
    """Report ``fraction`` (clamped to 0..1) when someone listens."""
    if progress is not None:
        progress(min(max(fraction, 0.0), 1.0))


def mesh_from_artifacts(artifacts: Mapping[str, NDArray[Any]]) -> TriangleMesh:
    """The latest mesh in the merged artifacts (colours and normals when present)."""
    vertices, faces = require_keys(artifacts, ("vertices_m", "faces"), "export")
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int32)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError("artifacts: vertices_m and faces must be (V, 3) and (F, 3)")
    colors = artifacts.get("vertex_colors")
    normals = artifacts.get("vertex_normals")
    ok_colors = colors is not None and len(colors) == len(vertices)
    ok_normals = normals is not None and len(normals) == len(vertices)
    return TriangleMesh(vertices_m=vertices, faces=faces,
                        vertex_colors=np.asarray(colors, np.uint8) if ok_colors else None,
                        vertex_normals=np.asarray(normals, np.float32) if ok_normals else None)


def stage_stats(artifacts: Mapping[str, NDArray[Any]]) -> dict[str, Any]:
    """The JSON figures every stage wrote, by stage."""
    return {key.removeprefix("stats_"): json.loads(str(value))
            for key, value in artifacts.items() if key.startswith("stats_")}
