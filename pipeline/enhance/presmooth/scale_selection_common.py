"""The interface of the twicings' smoothing steps (`FieldOps`) and the helpers both of its
implementations use: scipy and numpy on the host (`scale_selection_numpy`) or torch on a
device (`scale_selection_torch`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class FieldOps:
    """Where the smoothing steps, nearly all of the work, and the features run on (V, C)
    per-vertex fields: scipy and numpy on the host (`scale_selection_numpy.mesh_field_ops`),
    or torch on a device (`scale_selection_torch.mesh_field_ops`)."""

    step: Callable[[Any], Any]
    """y + lam (M y - y - c), lam = 0.5, with M the mean operator and c a fixed offset per
    vertex in each whole (x, y, z) triple of columns: positions (V, 3) take it, a (V, 1)
    field (the noise probe) has no whole triple and none; float64."""
    average: Callable[[Any], Any]
    """M y, float32: it serves only the features, which the selector reads in float32, and
    float32 halves what each pass reads."""
    to_field: Callable[[NDArray], Any]
    """A field there, its dtype kept."""
    to_numpy: Callable[[Any], NDArray]
    mean: Callable[[Any], Any]
    """M y, float64."""
    normals: Callable[[Any], Any]
    """(V, 3) float64 unit vertex normals of positions y on the mesh's faces, rounded to
    float32 as `pipeline.geometry.mesh.vertex_normals`."""
    columns: Callable[[list[Any]], Any]
    """(V, C) float32 of C (V,) columns."""


def leaving_out(step: Callable[[Any], Any], offset_m: NDArray[np.float64] | None,
                to_field: Callable[[NDArray], Any]) -> Callable[[Any], Any]:
    """`step` followed by subtracting 0.5 c, c laid out in each whole (x, y, z) triple of a
    field's columns (none in a trailing column), made once per field width; `step` itself
    where there is no c. Only the rows where c is not zero (the boundary's) are touched, not
    every row."""
    if offset_m is None:
        return step
    rows = np.flatnonzero(np.any(offset_m != 0, axis=1))
    rows_there = to_field(rows)
    half_offsets: dict[int, Any] = {}

    def half_offset(columns: int) -> Any:
        if columns not in half_offsets:
            tiled = np.zeros((len(rows), columns))
            tiled[:, : 3 * (columns // 3)] = np.tile(0.5 * offset_m[rows], columns // 3)
            half_offsets[columns] = to_field(tiled)
        return half_offsets[columns]

    def stepped(y: Any) -> Any:
        out = step(y)
        out[rows_there] -= half_offset(y.shape[1])
        return out

    return stepped


def along(field: Any, normals: Any) -> Any:
    """(V,) each row of (V, 3) `field` dotted with its row of `normals` (numpy or torch),
    column by column: torch on the CPU reduces an (N, 3) array along its rows slowly."""
    return (field[:, 0] * normals[:, 0] + field[:, 1] * normals[:, 1]
            + field[:, 2] * normals[:, 2])
