"""glTF 2.0 binary (GLB) export, optionally Draco-compressed (reading it back: `gltf_read`).

The GLB is written by hand (JSON chunk + BIN chunk): the container is small, and this keeps
full control over the fields the Khronos validator is strict about (no ``byteOffset`` on
accessors without a ``bufferView``, 4-byte aligned vertex strides, POSITION min/max).
"""

from __future__ import annotations

import json
import os
import struct
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import DracoPy
import numpy as np
from numpy.typing import NDArray

from pipeline.geometry.mesh import TriangleMesh, vertex_normals
from pipeline.io.glb_format import (
    ARRAY_BUFFER,
    CHUNK_BIN,
    CHUNK_JSON,
    DRACO_EXTENSION,
    ELEMENT_ARRAY_BUFFER,
    FLOAT,
    GENERATOR,
    GLB_MAGIC,
    TRIANGLES,
    UBYTE,
    UINT,
    USHORT,
)
from pipeline.io.mesh_io import write_ply


@dataclass(frozen=True)
class DracoConfig:
    """Draco (KHR_draco_mesh_compression) settings."""

    position_quantization_bits: int = 14
    """Bits per position coordinate over the bounding cube's side (1..30); the largest error is
    half a step: side / (2**bits - 1) / 2."""
    normal_quantization_bits: int = 10
    """Bits for the octahedral normal encoding (1..30); 10 keeps angles within ~0.3 degree."""
    color_quantization_bits: int = 8
    """Bits kept per colour channel (1..8); below 8 the low levels are merged before encoding,
    which the entropy coder turns into a smaller file. 8 is lossless."""
    compression_level: int = 7
    """Draco speed/size trade-off, 0 (fastest) .. 10 (smallest)."""

    def __post_init__(self) -> None:
        for name, low, high in (
            ("position_quantization_bits", 1, 30),
            ("normal_quantization_bits", 1, 30),
            ("color_quantization_bits", 1, 8),
            ("compression_level", 0, 10),
        ):
            value = getattr(self, name)
            if not isinstance(value, int) or not low <= value <= high:
                raise ValueError(f"DracoConfig.{name} must be an integer in [{low}, {high}], "
                                 f"got {value!r}")


def encode_glb(
    mesh: TriangleMesh,
    *,
    draco: DracoConfig | None = DracoConfig(),  # noqa: B008 - frozen, so a shared default is safe
    extras: Mapping[str, Any] | None = None,
) -> bytes:
    """The mesh as GLB bytes: POSITION, NORMAL (computed when absent) and COLOR_0 (when present).

    With ``draco`` the primitive is Draco-compressed and the extension is both used and required;
    with ``draco=None`` it is a plain GLB. ``extras`` (JSON-serialisable) lands in
    ``asset.extras``.
    """
    _check_mesh(mesh)
    normals = mesh.vertex_normals
    if normals is None:
        normals = vertex_normals(mesh.vertices_m, mesh.faces)
    asset: dict[str, Any] = {"version": "2.0", "generator": GENERATOR}
    if extras is not None:
        try:
            json.dumps(extras)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"extras must be JSON-serialisable: {exc}") from exc
        asset["extras"] = dict(extras)
    if draco is None:
        doc, binary = _plain_primitive(mesh, normals)
    else:
        doc, binary = _draco_primitive(mesh, normals, draco)
    doc["asset"] = asset
    doc["scene"] = 0
    doc["scenes"] = [{"nodes": [0]}]
    doc["nodes"] = [{"mesh": 0, "name": "mesh"}]
    doc["materials"] = [{
        "name": "surface",
        "pbrMetallicRoughness": {
            "baseColorFactor": [1.0, 1.0, 1.0, 1.0],
            # glTF's default metallic=1 renders a vertex-coloured scan nearly black.
            "metallicFactor": 0.0,
            "roughnessFactor": 0.8,
        },
        # Reconstructions can have holes; show the inside rather than nothing.
        "doubleSided": True,
    }]
    doc["buffers"] = [{"byteLength": len(binary)}]
    return _pack_glb(doc, binary)


def write_glb(
    path: str | os.PathLike[str],
    mesh: TriangleMesh,
    draco: DracoConfig | None = DracoConfig(),  # noqa: B008
) -> None:
    """Writes :func:`encode_glb` to ``path``; readers never see a partial file."""
    _write_atomically(Path(path), encode_glb(mesh, draco=draco))


def write_mesh(
    path: str | os.PathLike[str],
    mesh: TriangleMesh,
    draco: DracoConfig | None = DracoConfig(),  # noqa: B008
) -> None:
    """Writes by suffix: ``.glb`` (Draco unless ``draco=None``) or ``.ply`` (``draco`` unused)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".glb":
        write_glb(path, mesh, draco=draco)
    elif suffix == ".ply":
        write_ply(path, mesh)
    else:
        raise ValueError(f"output {str(path)!r}: unsupported mesh format {suffix or '(none)'!r}, "
                         "use .glb or .ply")


def simplify(mesh: TriangleMesh, target_faces: int) -> TriangleMesh:
    """A level-of-detail variant with about ``target_faces`` faces (quadric decimation).

    Colours are carried along by the decimation; normals are dropped (recomputed on export).
    A mesh already at or below the target comes back unchanged.
    """
    import open3d as o3d  # heavy; only LOD generation needs it

    _check_mesh(mesh)
    if not isinstance(target_faces, int | np.integer) or target_faces < 1:
        raise ValueError(f"target_faces must be a positive integer, got {target_faces!r}")
    if target_faces >= mesh.face_count:
        return mesh
    o3d_mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.asarray(mesh.vertices_m, dtype=np.float64)),
        o3d.utility.Vector3iVector(np.asarray(mesh.faces, dtype=np.int32)),
    )
    if mesh.vertex_colors is not None:
        o3d_mesh.vertex_colors = o3d.utility.Vector3dVector(mesh.vertex_colors / 255.0)
    reduced = o3d_mesh.simplify_quadric_decimation(int(target_faces))
    reduced.remove_unreferenced_vertices()
    colors = None
    if mesh.vertex_colors is not None and reduced.has_vertex_colors():
        colors = np.clip(np.rint(np.asarray(reduced.vertex_colors) * 255.0), 0, 255)
        colors = colors.astype(np.uint8)
    return TriangleMesh(
        vertices_m=np.asarray(reduced.vertices, dtype=np.float64),
        faces=np.asarray(reduced.triangles, dtype=np.int32),
        vertex_colors=colors,
    )


def _check_mesh(mesh: TriangleMesh) -> None:
    vertices, faces = np.asarray(mesh.vertices_m), np.asarray(mesh.faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) == 0:
        raise ValueError(f"mesh.vertices_m must have shape (V>0, 3), got {vertices.shape}")
    if not np.all(np.isfinite(vertices)):
        raise ValueError("mesh.vertices_m holds non-finite values")
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise ValueError(f"mesh.faces must have shape (F>0, 3), got {faces.shape}")
    if not np.issubdtype(faces.dtype, np.integer):
        raise ValueError(f"mesh.faces must be integers, got {faces.dtype}")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise ValueError(f"mesh.faces index outside [0, {len(vertices)})")
    for name in ("vertex_colors", "vertex_normals"):
        values = getattr(mesh, name)
        if values is not None and np.shape(values) != vertices.shape:
            raise ValueError(f"mesh.{name} must have shape {vertices.shape}, "
                             f"got {np.shape(values)}")
    if mesh.vertex_colors is not None and np.asarray(mesh.vertex_colors).dtype != np.uint8:
        raise ValueError(f"mesh.vertex_colors must be uint8, got {mesh.vertex_colors.dtype}")


def _index_type(vertex_count: int) -> tuple[int, type[np.unsignedinteger[Any]]]:
    return (USHORT, np.uint16) if vertex_count <= 0xFFFF else (UINT, np.uint32)


def _plain_primitive(
    mesh: TriangleMesh, normals: NDArray[np.floating[Any]]
) -> tuple[dict[str, Any], bytes]:
    positions = np.ascontiguousarray(mesh.vertices_m, dtype=np.float32)
    count = len(positions)
    index_type, index_dtype = _index_type(count)
    # (bytes, target, byteStride or None)
    blocks: list[tuple[bytes, int, int | None]] = [
        (positions.tobytes(), ARRAY_BUFFER, None),
        (np.ascontiguousarray(normals, dtype=np.float32).tobytes(), ARRAY_BUFFER, None),
    ]
    accessors: list[dict[str, Any]] = [
        _accessor(FLOAT, count, "VEC3", positions.min(axis=0), positions.max(axis=0)),
        _accessor(FLOAT, count, "VEC3"),
    ]
    attributes = {"POSITION": 0, "NORMAL": 1}
    if mesh.vertex_colors is not None:
        # Vertex attribute strides must be multiples of 4: pad RGB to 4 bytes per vertex.
        padded = np.zeros((count, 4), dtype=np.uint8)
        padded[:, :3] = mesh.vertex_colors
        blocks.append((padded.tobytes(), ARRAY_BUFFER, 4))
        accessors.append({**_accessor(UBYTE, count, "VEC3"), "normalized": True})
        attributes["COLOR_0"] = len(accessors) - 1
    blocks.append((np.ascontiguousarray(mesh.faces, dtype=index_dtype).tobytes(),
                   ELEMENT_ARRAY_BUFFER, None))
    accessors.append(_accessor(index_type, mesh.face_count * 3, "SCALAR"))
    binary = bytearray()
    views = []
    for position, (block, target, stride) in enumerate(blocks):
        binary += b"\0" * (-len(binary) % 4)
        view: dict[str, Any] = {"buffer": 0, "byteOffset": len(binary), "byteLength": len(block),
                                "target": target}
        if stride is not None:
            view["byteStride"] = stride
        views.append(view)
        accessors[position]["bufferView"] = position
        binary += block
    binary += b"\0" * (-len(binary) % 4)
    primitive = {"attributes": attributes, "indices": len(accessors) - 1, "material": 0,
                 "mode": TRIANGLES}
    doc = {"accessors": accessors, "bufferViews": views, "meshes": [{"primitives": [primitive]}]}
    return doc, bytes(binary)


def _draco_primitive(
    mesh: TriangleMesh, normals: NDArray[np.floating[Any]], config: DracoConfig
) -> tuple[dict[str, Any], bytes]:
    colors = mesh.vertex_colors
    if colors is not None and config.color_quantization_bits < 8:
        levels = (1 << config.color_quantization_bits) - 1
        colors = np.rint(np.rint(colors * (levels / 255.0)) * (255.0 / levels)).astype(np.uint8)
    try:
        encoded = DracoPy.encode(
            np.asarray(mesh.vertices_m, dtype=np.float64),
            faces=np.asarray(mesh.faces, dtype=np.uint32),
            quantization_bits=config.position_quantization_bits,
            compression_level=config.compression_level,
            normals=np.asarray(normals, dtype=np.float64),  # only float64 normals get quantised
            normal_quantization_bits=config.normal_quantization_bits,
            colors=colors,
        )
    except DracoPy.EncodingFailedException as exc:
        # Draco refuses a mesh whose triangles all collapse once positions are quantised.
        raise ValueError(f"mesh: Draco cannot encode it ({exc}); all triangles are degenerate "
                         "at this position_quantization_bits") from None
    # Draco renumbers, may split vertices and assigns attribute ids itself: the accessors must
    # describe what a decoder gets back, so read it back.
    decoded = DracoPy.decode(encoded)
    points = np.asarray(decoded.points, dtype=np.float32)
    count = len(points)
    ids = {int(a["attribute_type"]): int(a["unique_id"]) for a in decoded.attributes}
    index_type, _ = _index_type(count)
    accessors = [
        _accessor(FLOAT, count, "VEC3", points.min(axis=0), points.max(axis=0)),
        _accessor(FLOAT, count, "VEC3"),
    ]
    attributes = {"POSITION": 0, "NORMAL": 1}
    draco_ids = {"POSITION": ids[_DRACO_POSITION], "NORMAL": ids[_DRACO_NORMAL]}
    if colors is not None:
        accessors.append({**_accessor(UBYTE, count, "VEC3"), "normalized": True})
        attributes["COLOR_0"] = 2
        draco_ids["COLOR_0"] = ids[_DRACO_COLOR]
    accessors.append(_accessor(index_type, int(np.asarray(decoded.faces).size), "SCALAR"))
    primitive = {
        "attributes": attributes,
        "indices": len(accessors) - 1,
        "material": 0,
        "mode": TRIANGLES,
        "extensions": {DRACO_EXTENSION: {"bufferView": 0, "attributes": draco_ids}},
    }
    binary = encoded + b"\0" * (-len(encoded) % 4)
    doc = {
        "extensionsUsed": [DRACO_EXTENSION],
        "extensionsRequired": [DRACO_EXTENSION],
        "accessors": accessors,
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": len(encoded)}],
        "meshes": [{"primitives": [primitive]}],
    }
    return doc, binary


# Draco's GeometryAttribute::Type values, as DracoPy reports them in `attribute_type`.
_DRACO_POSITION, _DRACO_NORMAL, _DRACO_COLOR = 0, 1, 2


def _accessor(
    component_type: int,
    count: int,
    kind: str,
    low: NDArray[np.float32] | None = None,
    high: NDArray[np.float32] | None = None,
) -> dict[str, Any]:
    # No "byteOffset" key: accessors of a Draco primitive must not carry one at all.
    accessor: dict[str, Any] = {"componentType": component_type, "count": count, "type": kind}
    if low is not None and high is not None:
        accessor["min"] = [float(v) for v in low]
        accessor["max"] = [float(v) for v in high]
    return accessor


def _pack_glb(doc: dict[str, Any], binary: bytes) -> bytes:
    text = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    text += b" " * (-len(text) % 4)
    binary += b"\0" * (-len(binary) % 4)
    total = 12 + 8 + len(text) + 8 + len(binary)
    return b"".join([
        struct.pack("<III", GLB_MAGIC, 2, total),
        struct.pack("<II", len(text), CHUNK_JSON), text,
        struct.pack("<II", len(binary), CHUNK_BIN), binary,
    ])


def _write_atomically(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temp_name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(handle, "wb") as out:
            out.write(data)
        os.replace(temp_name, path)
    except BaseException:
        Path(temp_name).unlink(missing_ok=True)
        raise
