"""Reading triangle meshes (OBJ, PLY, STL, OFF, GLB ... via trimesh) and writing binary PLY."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from pipeline.geometry.mesh import TriangleMesh


def read_mesh(path: str | Path) -> TriangleMesh:
    """Reads a triangle mesh, merging duplicate vertices (also across texture and normal seams);
    all objects of the file are joined.

    Vertex colours are kept when the file has them; normals are dropped (stages recompute
    them from the merged connectivity). Raises ValueError naming the file when it cannot be
    read or holds no triangles.
    """
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: mesh file not found")
    try:
        loaded = trimesh.load(path, force="mesh", process=True)
    except Exception as exc:  # trimesh raises many kinds on malformed files
        raise ValueError(f"{path}: not a readable mesh ({exc})") from None
    if not isinstance(loaded, trimesh.Trimesh):
        raise ValueError(f"{path}: holds no triangle mesh")
    # trimesh keeps a vertex split where its texture coordinates or normals differ (UV seams,
    # creases); the geometry stages would see each seam as an open boundary.
    loaded.merge_vertices(merge_tex=True, merge_norm=True)
    faces = np.asarray(loaded.faces, dtype=np.int64)
    vertices = np.asarray(loaded.vertices, dtype=np.float64)
    if faces.size == 0 or vertices.size == 0:
        raise ValueError(f"{path}: mesh has no triangles")
    if not np.all(np.isfinite(vertices)):
        raise ValueError(f"{path}: vertex positions are not all finite")
    colors = _vertex_colors(loaded)
    return TriangleMesh(vertices_m=vertices, faces=faces.astype(np.int32), vertex_colors=colors)


def _vertex_colors(loaded: object) -> NDArray[np.uint8] | None:
    visual = getattr(loaded, "visual", None)
    if visual is None or getattr(visual, "kind", None) != "vertex":
        return None
    colors = np.asarray(visual.vertex_colors)
    if colors.ndim != 2 or colors.shape[1] < 3:
        return None
    return np.ascontiguousarray(colors[:, :3], dtype=np.uint8)


def write_ply(path: str | Path, mesh: TriangleMesh) -> None:
    """Writes a little-endian binary PLY: float32 positions, normals and uint8 RGB when present."""
    vertices = np.asarray(mesh.vertices_m)
    faces = np.asarray(mesh.faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"mesh.vertices_m: expected (V, 3), got {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"mesh.faces: expected (F, 3), got {faces.shape}")
    fields: list[tuple[str, str]] = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    columns: list[NDArray[np.generic]] = [vertices[:, i].astype("<f4") for i in range(3)]
    for name, array, dtype in (("n", mesh.vertex_normals, "<f4"),
                               ("c", mesh.vertex_colors, "u1")):
        if array is None:
            continue
        if array.shape != vertices.shape:
            raise ValueError(f"mesh: {name}: per-vertex array has shape {array.shape}, "
                             f"expected {vertices.shape}")
        names = ("nx", "ny", "nz") if name == "n" else ("red", "green", "blue")
        fields += [(n, dtype) for n in names]
        columns += [array[:, i].astype(dtype) for i in range(3)]
    vertex_table = np.empty(len(vertices), dtype=np.dtype(fields))
    for (name, _), column in zip(fields, columns, strict=True):
        vertex_table[name] = column
    face_table = np.empty(len(faces), dtype=np.dtype([("n", "u1"), ("idx", "<i4", (3,))]))
    face_table["n"] = 3
    face_table["idx"] = faces
    ply_types = {"<f4": "float", "u1": "uchar"}
    header = ["ply", "format binary_little_endian 1.0", "comment volumesh",
              f"element vertex {len(vertices)}"]
    header += [f"property {ply_types[dtype]} {name}" for name, dtype in fields]
    header += [f"element face {len(faces)}", "property list uchar int vertex_indices",
               "end_header"]
    with open(path, "wb") as out:
        out.write(("\n".join(header) + "\n").encode("ascii"))
        out.write(vertex_table.tobytes())
        out.write(face_table.tobytes())
