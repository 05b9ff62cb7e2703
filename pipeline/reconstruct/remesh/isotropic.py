"""Remeshing: isotropic remeshing to a target edge length, angle criteria.

The kernel is gpytoolbox's ``remesh_botsch`` (edge split, collapse, flip, tangential
relaxation, projection back onto the input), given boundary edges no longer than it would
leave interior ones (it holds the boundary). It is native code that can crash the whole
process on some inputs (cow.obj), so the mesh is repaired first and the kernel runs in a
child process: a crash, an error or a timeout there leaves the caller running, with the
repaired input returned and a warning in the stats. Minimum/maximum angle criteria are then
enforced by :mod:`pipeline.reconstruct.remesh.angle_cleanup`.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.geometry.mesh import TriangleMesh
from pipeline.geometry.order import corners_reordered, in_spatial_order
from pipeline.geometry.repair import repair, row_max, row_min, triangle_angles_deg
from pipeline.reconstruct.remesh.angle_cleanup import enforce_angles
from pipeline.reconstruct.remesh.boundary_split import split_boundary_edges
from pipeline.reconstruct.remesh.kernel import (
    Faces,
    FloatArray,
    KernelChild,
    KernelOutcome,
    KernelResult,
    furthest_from_m,
    measured_kernel,
    start_isolated,
)


@dataclass(frozen=True)
class RemeshConfig:
    """How the mesh is remeshed."""

    target_edge_length_m: float = 0.012
    """Edge length the remeshing aims for, metres."""
    iterations: int = 2
    """Split/collapse/flip/relax rounds of the kernel."""
    min_angle_deg: float = 20.0
    """Triangles with a smaller angle are collapsed away after remeshing."""
    max_angle_deg: float = 120.0
    """Triangles with a larger angle get their long edge flipped after remeshing."""
    cleanup_passes: int = 3
    """Rounds of the angle clean-up."""
    max_kernel_added_outside: float | None = None
    """Drop the kernel's result where it leaves a share of faces outside the angle criteria
    greater by more than this than the share it was given, and clean up its input instead
    (None: always keep it). For a light remesh at the mesh's own edge length, whose one job
    is the triangles' shape."""
    max_kernel_lost_edges: float | None = None
    """Drop the kernel's result (and clean up its input instead) where a vertex of its input
    lies further than this many target edge lengths from every vertex of the result
    (`surface_lost_edges`): the kernel projects onto its input, so it has cut part of the
    surface away or left faces far longer than the target, as one round of it does where
    its input has faces tens of edges long (None: no check)."""
    min_component_share: float = 0.0
    """Pieces smaller than this share of the largest (in faces) are dropped first (0: none;
    the mesh stage drops the pieces nothing was seen on, and a scene's true pieces may be
    small beside its largest)."""
    isolate: bool = True
    """Run the native kernel in a child process so a crash cannot take the caller down."""
    timeout_s: float = 300.0
    """The child is stopped after this long and the input is kept."""
    kernel_processes: int | None = 1
    """Children the isolated kernel's work is split over, each remeshing a spatial piece with
    the cuts held (`pieces`; None: one per core, at most one per `MIN_PIECE_FACES`
    faces; `kernel_piece_count`). Only for a target near the mesh's own edge length: a
    remesh to a much longer one would keep a seam of short edges along each cut."""

    def __post_init__(self) -> None:
        if not self.target_edge_length_m > 0:
            raise ValueError("remesh: target_edge_length_m must be > 0")
        if self.iterations < 0 or self.cleanup_passes < 0:
            raise ValueError("remesh: iterations and cleanup_passes must be >= 0")
        if not 0 <= self.min_angle_deg < 60 < self.max_angle_deg <= 180:
            raise ValueError("remesh: need 0 <= min_angle_deg < 60 < max_angle_deg <= 180")
        if self.max_kernel_added_outside is not None and not 0 <= self.max_kernel_added_outside < 1:
            raise ValueError("remesh: max_kernel_added_outside must be None or in [0, 1)")
        if self.max_kernel_lost_edges is not None and not self.max_kernel_lost_edges > 0:
            raise ValueError("remesh: max_kernel_lost_edges must be None or > 0")
        if not self.timeout_s > 0:
            raise ValueError("remesh: timeout_s must be > 0")
        if self.kernel_processes is not None and self.kernel_processes < 1:
            raise ValueError("remesh: kernel_processes must be None or >= 1")


MIN_PIECE_FACES = 25_000
"""Faces a piece of the kernel's work has at least (`kernel_processes`): a child takes about
0.2 s to start, the kernel about 5 us a face, so a smaller piece would spend more on its child
than it saves. The enhancement starts its children ahead (`kernel.kernel_children`), so their
start is off the way (`benchmarks/remesh_speed.py` times the split)."""


def kernel_piece_count(face_count: int, processes: int | None) -> int:
    """How many pieces `start_kernel` cuts a mesh of `face_count` faces into: `processes`
    (at most one a face), or for None one per core this process may use, at most one per
    `MIN_PIECE_FACES` faces."""
    if processes is not None:
        return max(1, min(processes, face_count))
    return max(1, min(len(os.sched_getaffinity(0)), face_count // MIN_PIECE_FACES))


def start_kernel(vertices_m: FloatArray, faces: Faces, config: RemeshConfig,
                 children: Sequence[KernelChild] = (), measure_lost: bool = False
                 ) -> Callable[[], KernelOutcome]:
    """`start_isolated` on the whole mesh, or, where it is cut into more than one piece
    (`kernel_piece_count`), the boundary split here, then `start_pieces`. The started
    `children` are used first (the caller ends any left), then new ones."""
    count = kernel_piece_count(len(faces), config.kernel_processes)
    if count == 1:
        return start_isolated(vertices_m, faces, config.target_edge_length_m,
                              config.iterations, config.timeout_s,
                              child=children[0] if children else None,
                              measure_lost=measure_lost)
    vertices_m, faces, _ = in_spatial_order(
        *split_boundary_edges(vertices_m, faces, config.target_edge_length_m))
    return start_pieces(vertices_m, faces, count, config, children, measure_lost)


def start_pieces(vertices_m: FloatArray, faces: Faces, count: int, config: RemeshConfig,
                 children: Sequence[KernelChild] = (), measure_lost: bool = False,
                 locate: bool = False) -> Callable[[], KernelOutcome]:
    """The kernel on a mesh already split (`split_boundary_edges`) and in a spatial order,
    one child per spatial piece (`pieces`), and a call that waits for them and joins
    them. One piece failing fails the whole. Where `locate`, the joined result's vertices
    come as points of the input's faces (`source_ids` index `vertices_m`).

    Each piece's `lost_m` (`measure_lost`) is measured against its own result, a part of the
    whole's, so the joined figure, their greatest, can only be above the whole's: at most by
    an edge, near a cut, where the cut's held vertices are in both."""
    from pipeline.reconstruct.remesh.pieces import spatial_pieces, stitched, stitched_sources

    ready: list[KernelChild | None] = [*children[:count], *[None] * (count - len(children))]
    pieces = spatial_pieces(faces, count)
    waits = [start_isolated(vertices_m[p.vertex_ids], p.faces, config.target_edge_length_m,
                            config.iterations, config.timeout_s, split=False, child=child,
                            measure_lost=measure_lost, locate=locate)
             for p, child in zip(pieces, ready, strict=True)]

    def wait() -> KernelOutcome:
        outcomes = [w() for w in waits]
        failed = [f"piece {k}: {why}" for k, (_, why) in enumerate(outcomes) if why]
        if failed:
            return None, "; ".join(failed)
        results = [r for r, _ in outcomes if r is not None]
        try:
            joined_m, joined, rows = stitched(
                vertices_m, pieces, [(r.vertices_m, r.faces, r.held) for r in results])
        except ValueError as exc:
            return None, str(exc)
        # The stitch keeps the pieces' faces in their order, so their angles follow them.
        lost_m = max(r.lost_m or 0.0 for r in results) if measure_lost else None
        held = np.zeros(0, dtype=np.int64)  # the joined mesh's boundary is not asked for
        ids, weights = None, None
        if locate:
            ids, weights = stitched_sources(
                len(vertices_m), pieces,
                [(r.source_ids, r.source_weights, len(r.held)) for r in results
                 if r.source_ids is not None and r.source_weights is not None], rows)
        return KernelResult(joined_m, joined, held,
                            np.concatenate([r.angles_deg for r in results]), lost_m,
                            ids, weights), None

    return wait


def angle_stats(vertices_m: FloatArray, faces: Faces, config: RemeshConfig) -> dict[str, float]:
    """Smallest and largest angle, and the shares of faces outside the criteria."""
    return angle_figures(triangle_angles_deg(vertices_m, faces), config)


def angle_figures(angles: FloatArray, config: RemeshConfig) -> dict[str, float]:
    """`angle_stats` from the faces' (F, 3) `triangle_angles_deg`."""
    if len(angles) == 0:
        return {"min_angle_deg": 0.0, "max_angle_deg": 0.0, "share_below_min": 0.0,
                "share_above_max": 0.0}
    smallest, largest = row_min(angles), row_max(angles)
    return {"min_angle_deg": float(smallest.min()), "max_angle_deg": float(largest.max()),
            "share_below_min": float(np.mean(smallest < config.min_angle_deg)),
            "share_above_max": float(np.mean(largest > config.max_angle_deg))}


def _outside(angles: dict[str, float]) -> float:
    return angles["share_below_min"] + angles["share_above_max"]


def remesh(mesh: TriangleMesh, config: RemeshConfig, children: Sequence[KernelChild] = ()
           ) -> tuple[TriangleMesh, dict[str, Any]]:
    """The mesh remeshed isotropically; stats hold repairs, angle figures, any warning and,
    where the kernel runs in a child, the seconds the caller waited for it (`kernel_wait_s`).

    Where the kernel's result may be dropped (`max_kernel_added_outside`,
    `max_kernel_lost_edges`), the figures it is judged by are measured in its children
    (`KernelResult`), and the input is cleaned up only where it is dropped: cleaning it up
    beside the children, in case, would be the caller's longest step on many cores. The
    kernel's children may have been started ahead (`children`: `kernel.kernel_children`).
    """
    vertices, faces, removed = repair(mesh.vertices_m, mesh.faces, config.min_component_share)
    if len(faces) == 0:
        raise ValueError("mesh: nothing left to remesh after repair (degenerate input)")
    stats: dict[str, Any] = {"repair_removed_faces": removed, "warning": None}
    if config.iterations == 0:
        return cleaned_up(vertices, faces, config, stats)
    judged = (config.max_kernel_added_outside is not None
              or config.max_kernel_lost_edges is not None)
    measure_lost = config.max_kernel_lost_edges is not None
    given = None
    if config.isolate:
        wait = start_kernel(vertices, faces, config, children, measure_lost)
        given = triangle_angles_deg(vertices, faces) if judged else None
        waited_from = time.perf_counter()
        result, warning = wait()
        stats["kernel_wait_s"] = time.perf_counter() - waited_from
    else:
        result, warning = measured_kernel(vertices, faces, config.target_edge_length_m,
                                          config.iterations, split=True,
                                          measure_lost=measure_lost), None
    stats["warning"] = warning and f"{warning}; kept the unremeshed mesh"
    if result is not None and judged:
        given = triangle_angles_deg(vertices, faces) if given is None else given
        stats["kernel_kept"] = kernel_passes(angle_figures(given, config), result, config,
                                             stats)
        if not stats["kernel_kept"]:
            return cleaned_up(vertices, faces, config, stats, given)
    if result is not None:
        return cleaned_up(result.vertices_m, result.faces, config, stats, result.angles_deg,
                          in_order=True)
    return cleaned_up(vertices, faces, config, stats, given)


def surface_lost_edges(input_vertices_m: FloatArray, result_vertices_m: FloatArray,
                       edge_m: float) -> float:
    """How far the input vertex furthest from every vertex of the result lies from them, in
    edge lengths `edge_m`. Large where the result has cut part of the input's surface away, or
    kept faces far longer than `edge_m` (an upper bound of how far the input's vertices are
    from the result's surface). About 1 or less for a kernel round that kept the surface."""
    return furthest_from_m(input_vertices_m, result_vertices_m) / edge_m


def kernel_passes(given: dict[str, float], result: KernelResult, config: RemeshConfig,
                  stats: dict[str, Any]) -> bool:
    """Whether the kernel's result meets `max_kernel_added_outside` (against the angle
    figures it was `given`) and `max_kernel_lost_edges` (its `lost_m`, in target edge
    lengths, as `surface_lost_edges`); the figures go into `stats`."""
    passes = True
    if config.max_kernel_added_outside is not None:
        added = _outside(angle_figures(result.angles_deg, config)) - _outside(given)
        passes = added <= config.max_kernel_added_outside
    if config.max_kernel_lost_edges is not None:
        assert result.lost_m is not None  # asked for wherever the limit is set
        stats["kernel_lost_edges"] = result.lost_m / config.target_edge_length_m
        passes = passes and stats["kernel_lost_edges"] <= config.max_kernel_lost_edges
    return passes


def cleaned_up(vertices_m: FloatArray, faces: Faces, config: RemeshConfig,
               stats: dict[str, Any], angles: FloatArray | None = None, in_order: bool = False
               ) -> tuple[TriangleMesh, dict[str, Any]]:
    """The angle clean-up of a mesh, and `stats` with its angle figures added (`angles`: the
    faces' `triangle_angles_deg`, where they are already known). The mesh is put in a spatial
    order first unless it is `in_order`, as the kernel's results are: it keeps its input's
    spatial order, and sorting them again would cost as much as the clean-up gains."""
    angles = triangle_angles_deg(vertices_m, faces) if angles is None else angles
    stats["angles_before_cleanup"] = angle_figures(angles, config)
    if not in_order:
        vertices_m, faces, order = in_spatial_order(vertices_m, faces)
        angles = corners_reordered(angles, order)
    vertices_m, faces, angles, stats["angle_cleanup"] = enforce_angles(
        vertices_m, faces, angles, config.min_angle_deg, config.max_angle_deg,
        config.cleanup_passes)
    stats["angles"] = angle_figures(angles, config)
    return TriangleMesh(vertices_m=vertices_m, faces=faces), stats
