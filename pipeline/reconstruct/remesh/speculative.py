"""Speculative remesh: a remesh started before its mesh's vertices have their last positions,
the enhancement's light remesh started on the mesh its update is about to move.

The update moves the pre-smoothed mesh's vertices and keeps its faces; the light remesh then
remeshes the moved mesh at its own edge length. Its kernel (native, single-threaded, in
child processes) is most of the remesh's time, and on a GPU it would otherwise wait for the
update to end. Here it starts on the mesh the update will move, while the networks and the
update run, and its result is carried onto the moved mesh when that is ready (barycentric
transfer): the kernel projects each of its vertices onto the mesh it was given, so each lies
on one of that mesh's faces (`kernel.located_on`), and it goes to the point with the same
barycentric coordinates on that face of the moved mesh.

So the kernel's splits, collapses, flips and relaxation are chosen on the surface before the
update, which moves vertices by a fraction of an edge, and so is whether its result is kept
(`RemeshConfig.max_kernel_added_outside`, `max_kernel_lost_edges`). The angle clean-up runs
on the moved mesh, as in `isotropic.remesh`.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from pipeline.geometry.mesh import TriangleMesh
from pipeline.geometry.order import reordered, spatial_order
from pipeline.geometry.repair import (
    DEGENERATE_AREA_M2,
    edge_table,
    face_areas,
    is_repaired,
    repair,
    triangle_angles_deg,
)
from pipeline.reconstruct.remesh.boundary_split import split_boundary_edges_with_parents
from pipeline.reconstruct.remesh.isotropic import (
    RemeshConfig,
    angle_figures,
    cleaned_up,
    kernel_passes,
    kernel_piece_count,
    remesh,
    start_pieces,
)
from pipeline.reconstruct.remesh.kernel import Faces, FloatArray, KernelChild, KernelOutcome

Carry = Callable[[FloatArray, NDArray[np.int64], FloatArray, Faces], tuple[FloatArray, FloatArray]]
"""The kernel's result carried onto the moved mesh (`carried_with_angles`'s arguments and
outcome): a finish's one full-mesh step that another device can take (on a GPU,
`pipeline.enhance.clean.transfer_torch.carried_on`)."""


def carried_with_angles(vertices_m: FloatArray, source_ids: NDArray[np.int64],
                        source_weights: FloatArray, faces: Faces
                        ) -> tuple[FloatArray, FloatArray]:
    """(V', 3) the points with (V', 3) barycentric `source_weights` on the (V', 3) corners
    `source_ids` of (N, 3) `vertices_m`, and (F, 3) `triangle_angles_deg` of `faces` on them."""
    carried_m = np.einsum("vk,vkd->vd", source_weights, vertices_m[source_ids])
    return carried_m, triangle_angles_deg(carried_m, faces)


@dataclass(frozen=True)
class RemeshAhead:
    """A remesh whose kernel is running on a mesh whose vertices will move
    (`start_remesh_ahead`); `finish_remesh_ahead` ends it on the moved mesh."""

    config: RemeshConfig
    wait: Callable[[], KernelOutcome]
    """Waits for the kernel's outcome: its children's pieces, joined in a thread of their own
    as soon as the last child ends (`in_background`)."""
    midpoint_parents: NDArray[np.int64]
    """(N, 2) the ends of the edge each midpoint of the boundary split bisected."""
    vertex_order: NDArray[np.int64]
    """(V',) the split mesh's vertex at each place of the kernel's input (a spatial order)."""
    given: dict[str, float]
    """The angle figures of the mesh the kernel was given (`isotropic.angle_figures`)."""
    stats: dict[str, Any]


@dataclass(frozen=True)
class CheckedFaces:
    """What `start_remesh_ahead` needs of its mesh's faces alone, found beforehand from a mesh
    with the same faces (`checked_faces`): the enhancement finds it beside the render, as the
    update moves vertices and keeps the faces."""

    repaired: bool
    """`repair` (no small pieces dropped) leaves the faces as they are (`is_repaired`), so
    only their areas need checking once the vertices have moved."""
    edges: NDArray[np.int64]
    """(E, 2) the faces' undirected edges (`pipeline.geometry.repair.edge_table`)."""
    opposite: NDArray[np.int64]
    """(F, 3) the edge opposite each corner."""


def checked_faces(mesh: TriangleMesh) -> CheckedFaces:
    """`CheckedFaces` of `mesh`."""
    return CheckedFaces(is_repaired(mesh.vertices_m, mesh.faces), *edge_table(mesh.faces))


def start_remesh_ahead(mesh: TriangleMesh, config: RemeshConfig,
                       children: Sequence[KernelChild] = (),
                       checked: CheckedFaces | None = None) -> RemeshAhead | None:
    """The remesh's kernel started on `mesh` (repaired, long boundary edges split, in a
    spatial order, in pieces: `isotropic.start_pieces`), each result vertex located on the
    kernel's input. None where the repair drops a vertex, so that the moved mesh's vertices
    would not match, or where the kernel runs in this process or not at all (then remesh
    the moved mesh as it is, `isotropic.remesh`).

    `checked`: `mesh`'s faces, checked beforehand. Where they need no repair only their areas
    are checked here, not the whole repair, and the split reads their edge table. Everything
    after the children have their pieces (the input's angle figures) is off the kernel's
    way."""
    if config.iterations == 0 or not config.isolate:
        return None
    vertices_m, faces, removed = _repaired(mesh, config, checked is not None and checked.repaired)
    if len(vertices_m) != mesh.vertex_count:
        return None
    table = (checked.edges, checked.opposite) if checked and faces is mesh.faces else None
    split_m, split_faces, parents = split_boundary_edges_with_parents(
        vertices_m, faces, config.target_edge_length_m, table)
    split = TriangleMesh(vertices_m=split_m, faces=split_faces)
    order = spatial_order(split)
    kernel_input = reordered(split, order)
    count = kernel_piece_count(len(faces), config.kernel_processes)
    joined = start_pieces(kernel_input.vertices_m, kernel_input.faces, count, config, children,
                          measure_lost=config.max_kernel_lost_edges is not None, locate=True)
    # Joining the pieces (loading the children's arrays, stitching them and their sources) is
    # done while the networks and the update run, where the kernel ends before them, rather
    # than after them on the finish's way.
    wait = in_background(joined)
    given = angle_figures(triangle_angles_deg(vertices_m, faces), config)
    return RemeshAhead(config, wait, parents, order.vertex_order, given,
                       {"repair_removed_faces": removed, "warning": None})


def in_background(call: Callable[[], KernelOutcome]) -> Callable[[], KernelOutcome]:
    """`call` started now in a thread of its own, and a call that waits for its outcome (an
    exception it raised is raised there, and nowhere where no one waits). The thread is
    not a daemon: the interpreter's exit waits for the kernel's children, which end with
    their work, at their timeout or when `kernel_children` ends them."""
    pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="remesh-join")
    outcome = pool.submit(call)
    pool.shutdown(wait=False)
    return outcome.result


def _repaired(mesh: TriangleMesh, config: RemeshConfig, faces_repaired: bool
              ) -> tuple[FloatArray, Faces, dict[str, int]]:
    """`repair`'s output, with only the areas checked where the faces are known to need no
    repair and no small pieces are to be dropped: then `mesh`'s own arrays."""
    if (faces_repaired and config.min_component_share == 0
            and (face_areas(mesh.vertices_m, mesh.faces) > DEGENERATE_AREA_M2).all()):
        return mesh.vertices_m, mesh.faces, {"degenerate": 0, "duplicate": 0, "non_manifold": 0}
    return repair(mesh.vertices_m, mesh.faces, config.min_component_share)


def finish_remesh_ahead(ahead: RemeshAhead, moved: TriangleMesh,
                        carry: Carry = carried_with_angles
                        ) -> tuple[TriangleMesh, dict[str, Any]]:
    """The remesh ended on `moved`, the mesh given to `start_remesh_ahead` with its vertices
    moved: the kernel's result carried onto it (by `carry`) and cleaned up, or, where the
    kernel failed or is dropped, `moved` cleaned up alone (as `isotropic.remesh` does). Stats
    as `isotropic.remesh` gives them, the kernel's figures measured before the move."""
    config, stats = ahead.config, dict(ahead.stats)
    # The finish's own wait: the pieces are joined in `in_background`, so this holds the join
    # only where the kernel ended late.
    waited_from = time.perf_counter()
    result, warning = ahead.wait()
    stats["kernel_wait_s"] = time.perf_counter() - waited_from
    stats["warning"] = warning and f"{warning}; kept the unremeshed mesh"
    if result is not None and (config.max_kernel_added_outside is not None
                               or config.max_kernel_lost_edges is not None):
        stats["kernel_kept"] = kernel_passes(ahead.given, result, config, stats)
        if not stats["kernel_kept"]:
            result = None
    if result is None or result.source_ids is None or result.source_weights is None:
        out, cleanup_stats = remesh(moved, replace(config, iterations=0))
        return out, {**cleanup_stats, **stats}
    kernel_input_m = midpoints_extended(moved.vertices_m, ahead.midpoint_parents)[
        ahead.vertex_order]
    carried_m, angles = carry(kernel_input_m, result.source_ids, result.source_weights,
                              result.faces)
    return cleaned_up(carried_m, result.faces, config, stats, angles, in_order=True)


def midpoints_extended(vertices_m: FloatArray, parents: NDArray[np.int64]) -> FloatArray:
    """(V + N, 3) `vertices_m` followed by the N midpoints of `parents`' edges, each the mean
    of its ends, where an end may be an earlier midpoint (a split's rounds)."""
    out = np.concatenate([vertices_m, np.full((len(parents), 3), np.nan)])
    todo = np.arange(len(parents))
    while len(todo):
        value = out[parents[todo]].mean(axis=1)
        ready = ~np.isnan(value).any(axis=1)
        if not ready.any():
            raise ValueError("midpoints: a parent is a later midpoint or not finite")
        out[len(vertices_m) + todo[ready]] = value[ready]
        todo = todo[~ready]
    return out
