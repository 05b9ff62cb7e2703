"""Mesh reading (OBJ, PLY) and binary PLY writing."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from pipeline.geometry.mesh import TriangleMesh, vertex_normals
from pipeline.io.mesh_io import read_mesh, write_ply

BUNNY = Path(__file__).resolve().parents[4] / "shared" / "data" / "meshes" / "stanford-bunny.obj"


def _tetra(colors: bool = True, normals: bool = True) -> TriangleMesh:
    vertices = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]) * 0.37
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], dtype=np.int32)
    return TriangleMesh(
        vertices_m=vertices, faces=faces,
        vertex_colors=np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255], [9, 99, 199]], np.uint8)
        if colors else None,
        vertex_normals=vertex_normals(vertices, faces) if normals else None)


def _header(path: Path) -> str:
    data = path.read_bytes()
    return data[: data.index(b"end_header")].decode("ascii")


def test_ply_round_trip_keeps_geometry_and_colours(tmp_path: Path) -> None:
    mesh = _tetra()
    write_ply(tmp_path / "t.ply", mesh)
    header = _header(tmp_path / "t.ply")
    assert "binary_little_endian" in header
    for prop in ("nx", "ny", "nz", "red", "green", "blue"):
        assert f" {prop}\n" in header
    back = read_mesh(tmp_path / "t.ply")
    assert back.face_count == 4 and back.vertex_count == 4
    np.testing.assert_allclose(back.vertices_m, mesh.vertices_m, atol=1e-7)
    np.testing.assert_array_equal(back.faces, mesh.faces)
    np.testing.assert_array_equal(back.vertex_colors, mesh.vertex_colors)
    # Another reader agrees on the normals.
    loaded = trimesh.load(tmp_path / "t.ply", process=False)
    assert isinstance(loaded, trimesh.Trimesh) and mesh.vertex_normals is not None
    np.testing.assert_allclose(loaded.vertex_normals, mesh.vertex_normals, atol=1e-6)


def test_ply_without_colours_or_normals(tmp_path: Path) -> None:
    write_ply(tmp_path / "plain.ply", _tetra(colors=False, normals=False))
    header = _header(tmp_path / "plain.ply")
    assert "red" not in header and "nx" not in header
    back = read_mesh(tmp_path / "plain.ply")
    assert back.vertex_colors is None and back.vertex_count == 4


def test_obj_duplicate_vertices_are_merged(tmp_path: Path) -> None:
    # Two triangles of a square, each with its own copy of the shared corners.
    (tmp_path / "quad.obj").write_text(
        "o a\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3\nf 4 5 6\n")
    mesh = read_mesh(tmp_path / "quad.obj")
    assert mesh.vertex_count == 4 and mesh.face_count == 2
    assert mesh.faces.dtype == np.int32 and mesh.vertices_m.dtype == np.float64


def test_obj_texture_and_normal_seams_are_merged(tmp_path: Path) -> None:
    # The square's diagonal is a UV seam and a crease: each triangle has its own texture
    # coordinates and normals at the shared corners, which must not split the surface.
    (tmp_path / "seam.obj").write_text(
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\n"
        "vt 0 0\nvt 1 0\nvt 1 1\nvt 0.5 0.5\nvt 0.9 0.9\nvt 0 1\n"
        "vn 0 0 1\nvn 0 0.1 1\n"
        "f 1/1/1 2/2/1 3/3/1\nf 1/4/2 3/5/2 4/6/2\n")
    mesh = read_mesh(tmp_path / "seam.obj")
    assert mesh.vertex_count == 4 and mesh.face_count == 2
    edges = np.sort(mesh.faces[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert np.sum(counts == 2) == 1  # the diagonal is shared, not two boundary edges


@pytest.mark.parametrize("name, content", [("empty.obj", ""), ("junk.ply", "not a mesh at all"),
                                           ("points.obj", "v 0 0 0\nv 1 0 0\n")])
def test_unreadable_files_name_the_file(tmp_path: Path, name: str, content: str) -> None:
    (tmp_path / name).write_text(content)
    with pytest.raises(ValueError, match=name):
        read_mesh(tmp_path / name)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="nothing.obj"):
        read_mesh(tmp_path / "nothing.obj")


def test_write_refuses_mismatched_arrays(tmp_path: Path) -> None:
    bad = TriangleMesh(vertices_m=np.zeros((4, 3)), faces=np.zeros((1, 3), np.int32),
                       vertex_colors=np.zeros((3, 3), np.uint8))
    with pytest.raises(ValueError, match="per-vertex"):
        write_ply(tmp_path / "bad.ply", bad)


@pytest.mark.skipif(not BUNNY.is_file(), reason="shared test meshes not present")
def test_reads_the_bunny() -> None:
    mesh = read_mesh(BUNNY)
    assert mesh.vertex_count > 30_000 and mesh.face_count > 60_000
    assert mesh.faces.max() < mesh.vertex_count
