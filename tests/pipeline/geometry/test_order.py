import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.geometry.mesh import TriangleMesh
from pipeline.geometry.order import (
    MeshOrder,
    corners_reordered,
    in_spatial_order,
    morton_codes,
    reordered,
    restored,
    spatial_order,
)
from tests.pipeline.geometry.test_boundary import grid


def _random_mesh(seed: int, vertex_count: int, face_count: int) -> TriangleMesh:
    rng = np.random.default_rng(seed)
    return TriangleMesh(
        vertices_m=rng.normal(size=(vertex_count, 3)),
        faces=rng.integers(0, vertex_count, (face_count, 3)).astype(np.int32),
        vertex_colors=rng.integers(0, 256, (vertex_count, 3)).astype(np.uint8),
        vertex_normals=rng.normal(size=(vertex_count, 3)).astype(np.float32))


def _corner_positions(mesh: TriangleMesh) -> set[tuple[float, ...]]:
    """Each face as its corners' coordinates, its winding kept (its least rotation, which is
    one for a face that repeats a vertex, too)."""
    return {min(tuple(np.roll(corners, -start, axis=0).ravel()) for start in range(3))
            for corners in mesh.vertices_m[mesh.faces]}


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), vertex_count=st.integers(3, 60),
       face_count=st.integers(1, 80))
def test_reordering_keeps_the_surface_and_restoring_undoes_it(
        seed: int, vertex_count: int, face_count: int) -> None:
    mesh = _random_mesh(seed, vertex_count, face_count)
    order = spatial_order(mesh)
    moved = reordered(mesh, order)
    assert moved.faces.dtype == np.int32
    assert _corner_positions(moved) == _corner_positions(mesh)
    # Colours and normals travel with their vertices.
    def coloured(m: TriangleMesh) -> set[tuple[float, ...]]:
        return {tuple(row) for row in np.hstack([m.vertices_m, m.vertex_colors])}

    assert coloured(moved) == coloured(mesh)
    back = restored(moved, order)
    for name in ("vertices_m", "faces", "vertex_colors", "vertex_normals"):
        assert np.array_equal(getattr(back, name), getattr(mesh, name))


def _listed_otherwise(mesh: TriangleMesh, seed: int) -> TriangleMesh:
    """The same mesh with its vertices and faces listed in another order, and each face
    starting at another corner (its winding kept)."""
    rng = np.random.default_rng(seed)
    return reordered(mesh, MeshOrder(vertex_order=rng.permutation(mesh.vertex_count),
                                     face_order=rng.permutation(mesh.face_count),
                                     face_start=rng.integers(0, 3, mesh.face_count)))


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), vertex_count=st.integers(3, 60),
       face_count=st.integers(1, 80), other=st.integers(0, 2**31 - 1))
def test_the_order_depends_on_the_surface_not_on_how_it_is_listed(
        seed: int, vertex_count: int, face_count: int, other: int) -> None:
    # Random faces repeat vertices and whole faces too: those are canonical as well.
    mesh = _random_mesh(seed, vertex_count, face_count)
    listed = _listed_otherwise(mesh, other)
    a, b = reordered(mesh, spatial_order(mesh)), reordered(listed, spatial_order(listed))
    for name in ("vertices_m", "faces", "vertex_colors", "vertex_normals"):
        assert np.array_equal(getattr(a, name), getattr(b, name))
    assert a.faces.dtype == np.int32


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), count=st.integers(2, 30))
def test_vertices_sharing_a_cell_are_ordered_by_their_coordinates(seed: int, count: int) -> None:
    rng = np.random.default_rng(seed)
    # A cloud a metre across whose first `count` points lie within 1e-9 m of one another:
    # one cell even of the finest (21-bit) grid, so the codes tie.
    cluster = 0.25 + rng.uniform(0, 1e-9, (count, 3))
    points = np.vstack([cluster, rng.uniform(0, 1, (20, 3)), [[0, 0, 0], [1, 1, 1]]])
    assert len(np.unique(morton_codes(points, 21)[:count])) == 1
    mesh = TriangleMesh(vertices_m=points, faces=np.array([[0, 1, count]], np.int32))
    ordered = reordered(mesh, spatial_order(mesh)).vertices_m
    in_cluster = ordered[np.isin(ordered, cluster).all(axis=1)]
    assert np.array_equal(in_cluster, cluster[np.lexsort(cluster.T[::-1])])


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(12, 40))
def test_the_spatial_order_brings_neighbours_together(seed: int, n: int) -> None:
    mesh = grid(n, 0.01)
    inverse = np.random.default_rng(seed).permutation(mesh.vertex_count)  # old -> new index
    shuffled = TriangleMesh(vertices_m=mesh.vertices_m[np.argsort(inverse)],
                            faces=inverse[mesh.faces].astype(np.int32))

    def mean_index_gap(m: TriangleMesh) -> float:
        return float(np.abs(m.faces - np.roll(m.faces, 1, axis=1)).mean())

    ordered = reordered(shuffled, spatial_order(shuffled))
    assert mean_index_gap(ordered) < 0.25 * mean_index_gap(shuffled)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), axis=st.integers(0, 2))
def test_morton_codes_grow_along_each_axis(seed: int, axis: int) -> None:
    rng = np.random.default_rng(seed)
    points = np.repeat(rng.uniform(-1, 1, (1, 3)), 50, axis=0)
    points[:, axis] = np.sort(rng.uniform(-1, 1, 50))
    # The bounding cube spans more than the line, as in a mesh.
    codes = morton_codes(np.vstack([points, [[-2.0, -2.0, -2.0], [2.0, 2.0, 2.0]]]))[:50]
    assert np.all(np.diff(codes.astype(np.int64)) >= 0)
    assert codes[-1] > codes[0]


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), bits=st.integers(1, 21))
def test_morton_codes_interleave_the_cells_bits(seed: int, bits: int) -> None:
    """Each code has bit b of the point's x, y and z cells at bits 3 b, 3 b + 1, 3 b + 2."""
    points = np.random.default_rng(seed).uniform(-1, 1, (200, 3))
    codes = morton_codes(points, bits)
    cells = np.minimum(((points - points.min(axis=0)) / np.ptp(points, axis=0).max()
                        * 2**bits).astype(np.int64), 2**bits - 1)
    for bit in range(bits):
        for axis in range(3):
            np.testing.assert_array_equal((codes.astype(np.int64) >> (3 * bit + axis)) & 1,
                                          (cells[:, axis] >> bit) & 1)
    assert codes.max() < 2 ** (3 * bits)


def test_an_empty_mesh_has_an_empty_order() -> None:
    empty = TriangleMesh(vertices_m=np.zeros((0, 3)), faces=np.zeros((0, 3), np.int32))
    order = spatial_order(empty)
    assert len(order.vertex_order) == 0 and len(order.face_order) == 0
    assert reordered(empty, order).vertex_count == 0


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), vertex_count=st.integers(3, 40),
       face_count=st.integers(1, 60))
def test_per_corner_values_move_with_their_faces(
        seed: int, vertex_count: int, face_count: int) -> None:
    from pipeline.geometry.repair import triangle_angles_deg

    mesh = _random_mesh(seed, vertex_count, face_count)
    vertices_m, faces, order = in_spatial_order(mesh.vertices_m, mesh.faces)
    np.testing.assert_array_equal(
        corners_reordered(triangle_angles_deg(mesh.vertices_m, mesh.faces), order),
        triangle_angles_deg(vertices_m, faces))


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), face_count=st.integers(1, 80))
def test_past_2_21_vertices_faces_take_three_keys_to_the_same_order(
        seed: int, face_count: int) -> None:
    from pipeline.geometry.order import _face_order

    rng = np.random.default_rng(seed)
    # Faces with three distinct vertices, as a mesh past 2^21 vertices would list them; the
    # three-key branch is asked for by the vertex count alone.
    corners = np.array([rng.choice(50, 3, replace=False) for _ in range(face_count)])
    packed_order, packed_start = _face_order(corners, 50)
    keyed_order, keyed_start = _face_order(corners, 2**22)
    np.testing.assert_array_equal(keyed_order, packed_order)
    np.testing.assert_array_equal(keyed_start, packed_start)
