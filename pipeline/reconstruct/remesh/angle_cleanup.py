"""Minimum/maximum triangle-angle criteria enforced after isotropic remeshing.

Isotropic remeshing leaves a few needles (one tiny angle, one short edge) and caps (one
angle near 180 degrees) where the target length meets boundaries and thin features. Caps
are removed by flipping the edge opposite their large angle, needles by collapsing their
shortest edge. Each pass works on an independent set of operations chosen in parallel
(worst triangle first), so it stays vectorised; a few passes settle it.

The operations take the faces' angles and hand them on with the rows of the faces they
changed recomputed: a pass touches a few hundred of a few hundred thousand faces, and
measuring every angle again would be a third of the clean-up's time. For the same reason each
operation builds its edge table over the faces around its candidates only
(`_near_edge_table`), and `enforce_angles` runs the passes on a patch around the faces
outside the criteria, not on the whole mesh.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from pipeline.geometry.mesh import face_normals
from pipeline.geometry.repair import (
    compact,
    edge_table,
    faces_at,
    faces_per_edge,
    grown_by_rings,
    row_max,
    row_min,
    triangle_angles_deg,
    without_rows,
)

FloatArray = NDArray[np.float64]
Faces = NDArray[np.int32]


def _rank_claims(priority: FloatArray, claims: list[NDArray[np.int64]], size: int
                 ) -> NDArray[np.bool_]:
    """Candidates that rank best (lowest priority) among all that claim any shared item."""
    order = np.argsort(priority, kind="stable")
    rank = np.empty(len(priority), dtype=np.int64)
    rank[order] = np.arange(len(priority))
    best = np.full(size, len(priority), dtype=np.int64)
    for items in claims:
        np.minimum.at(best, items, rank)
    ok = np.ones(len(priority), dtype=bool)
    for items in claims:
        ok &= best[items] == rank
    return ok


def _near_edge_table(faces: Faces, cand_face: NDArray[np.int64], vertex_count: int
                     ) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64],
                                NDArray[np.int64]]:
    """`edge_table` of the faces that touch a vertex of the candidate faces: (N,) those
    faces, ascending, their (E, 2) edges and (N, 3) opposite-edge table, and (C,) each
    candidate's row in it. Every face at such a vertex is in it, so for each edge and vertex
    of the candidates it says what the whole mesh's table says (the faces that use an edge,
    whether a vertex is on the boundary, its neighbours, which pairs are edges), and its
    edges keep their order in the whole table. Away from them it is wrong: edges on the
    patch's own rim read as used once, like boundary edges, so the callers read what they
    derive from it only at their candidates. An operation has a few hundred candidates, and
    the whole mesh's tables would be most of the clean-up's time."""
    at = np.zeros(vertex_count, dtype=bool)
    at[faces[cand_face].ravel()] = True
    near = np.flatnonzero(faces_at(faces, at))
    edges, opposite = edge_table(faces[near])
    return near, edges, opposite, np.searchsorted(near, cand_face)


def flip_caps(vertices_m: FloatArray, faces: Faces, angles_deg: FloatArray,
              max_angle_deg: float) -> tuple[Faces, FloatArray, int]:
    """Flip the edge opposite each angle above max_angle_deg where that makes both faces
    better (larger smallest angle) and keeps the surface unfolded. `angles_deg` (F, 3) are
    the faces' `triangle_angles_deg`. Returns faces, their angles, flips."""
    angles = angles_deg
    cand_face = np.nonzero(row_max(angles) > max_angle_deg)[0]
    if len(cand_face) == 0:
        return faces, angles, 0
    near, edges, opposite, row = _near_edge_table(faces, cand_face, len(vertices_m))
    counts = faces_per_edge(opposite, len(edges))
    corner = np.argmax(angles[cand_face], axis=1)
    edge = opposite[row, corner]
    interior = counts[edge] == 2
    cand_face, row, corner, edge = (x[interior] for x in (cand_face, row, corner, edge))
    # Both faces of an edge may ask for the same flip: keep one request per edge.
    _, once = np.unique(edge, return_index=True)
    cand_face, row, corner, edge = cand_face[once], row[once], corner[once], edge[once]
    # An interior edge has two half-edges (row * 3 + corner): the other is their sum less this.
    half_sums = np.bincount(opposite.ravel(), weights=np.arange(opposite.size, dtype=np.float64),
                            minlength=len(edges))
    half = half_sums[edge].astype(np.int64) - (row * 3 + corner)
    other_face, other_corner = near[half // 3], half % 3
    p = faces[cand_face, corner]
    a = faces[cand_face, (corner + 1) % 3]
    b = faces[cand_face, (corner + 2) % 3]
    q = faces[other_face, other_corner]
    new_f = np.column_stack([p, a, q]).astype(np.int32)
    new_g = np.column_stack([p, q, b]).astype(np.int32)
    old_min = np.minimum(row_min(angles[cand_face]), row_min(angles[other_face]))
    f_angles = triangle_angles_deg(vertices_m, new_f)
    g_angles = triangle_angles_deg(vertices_m, new_g)
    new_min = np.minimum(row_min(f_angles), row_min(g_angles))
    old_n = face_normals(vertices_m, faces[cand_face]) + face_normals(vertices_m,
                                                                      faces[other_face])
    unfolded = ((np.sum(face_normals(vertices_m, new_f) * old_n, axis=1) > 0.5)
                & (np.sum(face_normals(vertices_m, new_g) * old_n, axis=1) > 0.5))
    pair_key = np.minimum(p, q).astype(np.int64) * (len(vertices_m) + 1) + np.maximum(p, q)
    # Ascending, as `edge_table` sorts its edges: a binary search finds the new pair's edge.
    existing = edges[:, 0] * (len(vertices_m) + 1) + edges[:, 1]
    at = np.minimum(np.searchsorted(existing, pair_key), len(existing) - 1)
    fresh = (existing[at] != pair_key) & (p != q)
    _, key_counts = np.unique(pair_key, return_counts=True)
    unique_new = key_counts[np.searchsorted(np.unique(pair_key), pair_key)] == 1
    good = (new_min > old_min) & unfolded & fresh & unique_new
    chosen = np.nonzero(good)[0]
    chosen = chosen[_rank_claims(-row_max(angles[cand_face[chosen]]),
                                 [cand_face[chosen], other_face[chosen]], len(faces))]
    out, out_angles = faces.copy(), angles.copy()
    out[cand_face[chosen]], out_angles[cand_face[chosen]] = new_f[chosen], f_angles[chosen]
    out[other_face[chosen]], out_angles[other_face[chosen]] = new_g[chosen], g_angles[chosen]
    return out, out_angles, len(chosen)


def collapse_needles(vertices_m: FloatArray, faces: Faces, angles_deg: FloatArray,
                     min_angle_deg: float
                     ) -> tuple[FloatArray, Faces, FloatArray, NDArray[np.bool_], int]:
    """Collapse the shortest edge of each face with an angle below min_angle_deg to its
    midpoint, where both ends are interior, the link condition holds and no face folds.
    `angles_deg` (F, 3) are the faces' `triangle_angles_deg`. Returns the mesh (the merged
    ends left in its vertices, used by no face), its faces' angles, (F,) the input's faces
    that are kept, and collapses."""
    angles = angles_deg
    all_kept = np.ones(len(faces), dtype=bool)
    cand_face = np.nonzero(row_min(angles) < min_angle_deg)[0]
    if len(cand_face) == 0:
        return vertices_m, faces, angles, all_kept, 0
    _, edges, opposite, row = _near_edge_table(faces, cand_face, len(vertices_m))
    counts = faces_per_edge(opposite, len(edges))
    # Right at the candidates' vertices, which are all that is read of it.
    boundary_vertex = np.zeros(len(vertices_m), dtype=bool)
    boundary_vertex[edges[counts == 1].ravel()] = True
    edge = np.unique(opposite[row, np.argmin(angles[cand_face], axis=1)])
    a, b = edges[edge, 0], edges[edge, 1]
    # A boundary end stays where it is (the kept end, a); two boundary ends are left alone.
    swap = boundary_vertex[b]
    a, b = np.where(swap, b, a), np.where(swap, a, b)
    keep = ~boundary_vertex[b] & (counts[edge] == 2)
    a, b = a[keep], b[keep]
    if len(a) == 0:
        return vertices_m, faces, angles, all_kept, 0
    from scipy.sparse import coo_matrix

    n = len(vertices_m)
    adj = coo_matrix((np.ones(2 * len(edges)), (np.concatenate([edges[:, 0], edges[:, 1]]),
                                                np.concatenate([edges[:, 1], edges[:, 0]]))),
                     shape=(n, n)).tocsr()
    common = np.asarray(adj[a].multiply(adj[b]).sum(axis=1)).ravel()
    link_ok = common == 2
    a, b = a[link_ok], b[link_ok]
    length = np.linalg.norm(vertices_m[a] - vertices_m[b], axis=1)
    # Claim each end and its one-ring, so no two collapses touch the same faces.
    ring_best = _ring_exclusive(length, a, b, edges, n)
    a, b = a[ring_best], b[ring_best]
    new_pos, new_faces, alive = _apply_collapses(vertices_m, faces, a, b, boundary_vertex)
    folded = alive & _turned(vertices_m, faces, new_pos, new_faces, a, b)
    if folded.any():
        # Leave out the collapses that would fold a face, then apply the rest.
        touched = np.zeros(n, dtype=bool)
        touched[faces[folded].ravel()] = True
        ok = ~(touched[a] | touched[b])
        a, b = a[ok], b[ok]
        new_pos, new_faces, alive = _apply_collapses(vertices_m, faces, a, b, boundary_vertex)
    # The merged ends stay in the array, used by no face: `enforce_angles` compacts once at
    # its end, quicker than compacting after every pass.
    out_f = new_faces[alive]
    out_angles = angles[alive]
    # Only faces at a kept end changed: it moved, or took the faces of the end merged into it.
    kept_end = np.zeros(n, dtype=bool)
    kept_end[a] = True
    changed = kept_end[out_f].any(axis=1)
    out_angles[changed] = triangle_angles_deg(new_pos, out_f[changed])
    return new_pos, out_f, out_angles, alive, len(a)


def _turned(vertices_m: FloatArray, faces: Faces, new_pos: FloatArray, new_faces: Faces,
            a: NDArray[np.int64], b: NDArray[np.int64]) -> NDArray[np.bool_]:
    """(F,) faces whose normal the collapses of (a, b) turn by more than about 72 degrees
    (or leave degenerate): only faces at a or b can change, so only they are measured."""
    at_ends = np.zeros(len(vertices_m), dtype=bool)
    at_ends[a] = at_ends[b] = True
    near = np.nonzero(faces_at(faces, at_ends))[0]
    before = face_normals(vertices_m, faces[near])
    after = face_normals(new_pos, new_faces[near])
    turned = np.zeros(len(faces), dtype=bool)
    turned[near] = np.sum(before * after, axis=1) < 0.3
    return turned


def _apply_collapses(vertices_m: FloatArray, faces: Faces, a: NDArray[np.int64],
                     b: NDArray[np.int64], boundary_vertex: NDArray[np.bool_]
                     ) -> tuple[FloatArray, Faces, NDArray[np.bool_]]:
    """Vertices b merged into a (at the midpoint, or at a when a is on the boundary)."""
    new_pos = vertices_m.copy()
    new_pos[a] = np.where(boundary_vertex[a][:, None], vertices_m[a],
                          0.5 * (vertices_m[a] + vertices_m[b]))
    target = np.arange(len(vertices_m))
    target[b] = a
    new_faces = target[faces].astype(np.int32)
    alive = ((new_faces[:, 0] != new_faces[:, 1]) & (new_faces[:, 1] != new_faces[:, 2])
             & (new_faces[:, 2] != new_faces[:, 0]))
    return new_pos, new_faces, alive


def _ring_exclusive(priority: FloatArray, a: NDArray[np.int64], b: NDArray[np.int64],
                    edges: NDArray[np.int64], vertex_count: int) -> NDArray[np.bool_]:
    """Candidates (a, b) best ranked among all candidates within one ring of a or b."""
    order = np.argsort(priority, kind="stable")
    rank = np.empty(len(priority), dtype=np.int64)
    rank[order] = np.arange(len(priority))
    best = np.full(vertex_count, len(priority), dtype=np.int64)
    np.minimum.at(best, a, rank)
    np.minimum.at(best, b, rank)
    spread = best.copy()
    np.minimum.at(spread, edges[:, 0], best[edges[:, 1]])
    np.minimum.at(spread, edges[:, 1], best[edges[:, 0]])
    return np.asarray((spread[a] == rank) & (spread[b] == rank))


def drop_boundary_slivers(vertices_m: FloatArray, faces: Faces, angles_deg: FloatArray,
                          min_angle_deg: float, max_angle_deg: float
                          ) -> tuple[Faces, FloatArray, NDArray[np.bool_], int]:
    """Remove faces outside the angle criteria that lie on the mesh boundary, where neither
    a flip nor a collapse can fix them: ears (two boundary edges), and faces with one
    boundary edge whose opposite vertex is interior (removing them keeps it manifold).
    `angles_deg` (F, 3) are the faces' `triangle_angles_deg`. Returns faces, their angles,
    (F,) the input's faces that are kept, and drops."""
    angles = angles_deg
    keep = np.ones(len(faces), dtype=bool)
    cand = np.nonzero(_outside(angles, min_angle_deg, max_angle_deg))[0]
    if len(cand) == 0:
        return faces, angles, keep, 0
    _, edges, opposite, row = _near_edge_table(faces, cand, len(vertices_m))
    counts = faces_per_edge(opposite, len(edges))
    on_boundary = counts[opposite[row]] == 1  # (C, 3): edge opposite each corner is a boundary
    boundary_vertex = np.zeros(len(vertices_m), dtype=bool)
    boundary_vertex[edges[counts == 1].ravel()] = True
    n_boundary = on_boundary.sum(axis=1)
    apex = faces[cand, np.argmax(on_boundary, axis=1)]
    cand = cand[(n_boundary == 2) | ((n_boundary == 1) & ~boundary_vertex[apex])]
    if len(cand) == 0:
        return faces, angles, keep, 0
    priority = row_min(angles[cand])
    chosen = cand[_rank_claims(priority, [faces[cand, 0], faces[cand, 1], faces[cand, 2]],
                               len(vertices_m))]
    keep[chosen] = False
    return faces[keep], angles[keep], keep, len(chosen)


def _outside(angles_deg: FloatArray, min_angle_deg: float, max_angle_deg: float
             ) -> NDArray[np.bool_]:
    """(F,) the faces with an angle outside the criteria."""
    return (row_min(angles_deg) < min_angle_deg) | (row_max(angles_deg) > max_angle_deg)


PATCH_RINGS = 2
"""How many rings around the faces outside the criteria `enforce_angles` works on. An
operation reads the faces at the corners of a face it fixes, and the faces it leaves outside
the criteria are next to it, so one ring is enough for a light remesh's passes. Where an
operation would reach the patch's rim all the same, the clean-up runs on the whole mesh."""


def _patch(faces: Faces, seed_faces: NDArray[np.bool_], vertex_count: int, rings: int
           ) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.bool_]]:
    """The faces near the (F,) `seed_faces`: (P,) the vertices they use, ascending, (R,) the
    faces, ascending, and (P,) which of the vertices are complete (within `rings` rings of a
    seed's corner, so every face of the mesh at them is in the patch)."""
    seeds = np.zeros(vertex_count, dtype=bool)
    seeds[faces[seed_faces].ravel()] = True
    near, at_near = grown_by_rings(faces, seeds, rings)
    rows = np.flatnonzero(at_near)
    used = np.zeros(vertex_count, dtype=bool)
    used[faces[rows].ravel()] = True
    vertices = np.flatnonzero(used)
    return vertices, rows, near[vertices]


def _reaches_rim(faces: Faces, angles_deg: FloatArray, min_angle_deg: float,
                 max_angle_deg: float, complete: NDArray[np.bool_] | None) -> bool:
    """Whether a face outside the criteria, which the next operation may take, has a corner
    not `complete`: there the patch's tables would not say what the mesh's say. This holds
    the patch to the whole mesh's result as long as every operation takes only faces
    outside the criteria and reads only the faces at their corners (the faces across their
    edges among them); an operation that reads further would need more rings checked."""
    if complete is None:
        return False
    return not complete[faces[_outside(angles_deg, min_angle_deg, max_angle_deg)]].all()


def _passes(vertices_m: FloatArray, faces: Faces, angles_deg: FloatArray, min_angle_deg: float,
            max_angle_deg: float, passes: int, complete: NDArray[np.bool_] | None
            ) -> tuple[FloatArray, Faces, FloatArray, NDArray[np.int64], dict[str, int]] | None:
    """`enforce_angles`' passes on a mesh or on a patch of one (`complete` as `_patch` gives
    it, None for a whole mesh): (V, 3) vertices, the merged ends left in them, the faces, their
    angles, (F',) the input rows they come from, and the operation counts; None where an
    operation would reach the patch's rim."""
    stats = {"flips": 0, "collapses": 0, "boundary_drops": 0}
    rows, angles = np.arange(len(faces)), angles_deg
    for _ in range(passes):
        if _reaches_rim(faces, angles, min_angle_deg, max_angle_deg, complete):
            return None
        faces, angles, flips = flip_caps(vertices_m, faces, angles, max_angle_deg)
        if _reaches_rim(faces, angles, min_angle_deg, max_angle_deg, complete):
            return None
        vertices_m, faces, angles, kept, collapses = collapse_needles(vertices_m, faces, angles,
                                                                      min_angle_deg)
        rows = rows[kept]
        if _reaches_rim(faces, angles, min_angle_deg, max_angle_deg, complete):
            return None
        faces, angles, kept, drops = drop_boundary_slivers(vertices_m, faces, angles,
                                                           min_angle_deg, max_angle_deg)
        rows = rows[kept]
        stats["flips"] += flips
        stats["collapses"] += collapses
        stats["boundary_drops"] += drops
        if flips == 0 and collapses == 0 and drops == 0:
            break
    return vertices_m, faces, angles, rows, stats


def enforce_angles(vertices_m: FloatArray, faces: Faces, angles_deg: FloatArray,
                   min_angle_deg: float, max_angle_deg: float, passes: int = 3
                   ) -> tuple[FloatArray, Faces, FloatArray, dict[str, int]]:
    """Flip caps, collapse needles, drop boundary slivers for a few passes, starting from the
    faces' `triangle_angles_deg` (`angles_deg`, (F, 3)); returns the mesh, its faces' angles
    and operation counts.

    The passes run on the faces within `PATCH_RINGS` rings of those outside the criteria,
    numbered in the mesh's order, so every choice is the one the whole mesh would give and
    the result is the same bit for bit, at a fraction of the time: a light remesh leaves a
    few dozen of a few hundred thousand faces outside the criteria."""
    outside = _outside(angles_deg, min_angle_deg, max_angle_deg)
    if not outside.any():
        out_v, out_f = compact(vertices_m, faces)
        return out_v, out_f, angles_deg, {"flips": 0, "collapses": 0, "boundary_drops": 0}
    vertices, rows, complete = _patch(faces, outside, len(vertices_m), PATCH_RINGS)
    local_id = np.zeros(len(vertices_m), dtype=np.int64)
    local_id[vertices] = np.arange(len(vertices))
    done = _passes(vertices_m[vertices], local_id[faces[rows]].astype(np.int32),
                   angles_deg[rows], min_angle_deg, max_angle_deg, passes, complete)
    if done is None:
        vertices, rows = np.arange(len(vertices_m)), np.arange(len(faces))
        done = _passes(vertices_m, faces, angles_deg, min_angle_deg, max_angle_deg, passes, None)
        assert done is not None  # a whole mesh has no rim
    patch_vertices_m, patch_faces, patch_angles, kept_rows, stats = done
    out_v = vertices_m.copy()
    out_v[vertices] = patch_vertices_m
    kept = np.zeros(len(rows), dtype=bool)
    kept[kept_rows] = True
    dropped, kept_at = rows[~kept], rows[kept_rows]
    out_f, out_angles = without_rows(faces, dropped), without_rows(angles_deg, dropped)
    # Where each kept row lands once the dropped ones are gone.
    out_row = kept_at - np.searchsorted(dropped, kept_at)
    out_f[out_row] = vertices[patch_faces]
    out_angles[out_row] = patch_angles
    out_v, out_f = compact(out_v, out_f)
    return out_v, out_f, out_angles, stats
