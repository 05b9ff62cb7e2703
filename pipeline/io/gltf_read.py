"""Reading GLB files (plain or Draco-compressed triangle primitives) back into one mesh, as
the tests, benchmarks and the CLI check what `gltf_io` wrote."""

from __future__ import annotations

import json
import struct
from typing import Any

import DracoPy
import numpy as np
from numpy.typing import NDArray

from pipeline.geometry.mesh import TriangleMesh
from pipeline.io.glb_format import (
    CHUNK_BIN,
    CHUNK_JSON,
    COMPONENTS,
    DRACO_EXTENSION,
    DTYPES,
    GLB_MAGIC,
    TRIANGLES,
)


def decode_glb(data: bytes) -> TriangleMesh:
    """Reads a GLB with triangle primitives (Draco or plain) into one mesh.

    Node transforms are ignored (our files have none); all triangle primitives of all meshes
    are concatenated. Colours come back as uint8 sRGB, normals as float32.
    """
    doc, binary = _unpack_glb(data)
    try:
        parts = [
            _read_primitive(doc, binary, prim)
            for mesh in doc.get("meshes", [])
            for prim in mesh.get("primitives", [])
            if prim.get("mode", TRIANGLES) == TRIANGLES
        ]
    except (KeyError, IndexError, TypeError, AttributeError) as exc:
        raise ValueError(f"GLB: malformed glTF JSON ({type(exc).__name__}: {exc})") from None
    if not parts:
        raise ValueError("GLB holds no triangle primitive")
    return _concatenate(parts)


def _unpack_glb(data: bytes) -> tuple[dict[str, Any], bytes]:
    if len(data) < 20:
        raise ValueError("GLB too short")
    magic, version, length = struct.unpack_from("<III", data, 0)
    if magic != GLB_MAGIC or version != 2:
        raise ValueError("GLB: not a glTF 2.0 binary (bad magic or version)")
    if length > len(data):
        raise ValueError(f"GLB truncated: header says {length} bytes, got {len(data)}")
    doc: dict[str, Any] | None = None
    binary = b""
    offset = 12
    while offset + 8 <= length:
        chunk_length, chunk_type = struct.unpack_from("<II", data, offset)
        chunk = data[offset + 8: offset + 8 + chunk_length]
        if len(chunk) != chunk_length:
            raise ValueError("GLB chunk runs past the end of the file")
        if chunk_type == CHUNK_JSON and doc is None:
            try:
                doc = json.loads(chunk.decode("utf-8"))
            except (UnicodeDecodeError, json.JSONDecodeError) as exc:
                raise ValueError(f"GLB JSON chunk is not valid JSON: {exc}") from exc
        elif chunk_type == CHUNK_BIN and not binary:
            binary = chunk
        offset += 8 + chunk_length
    if not isinstance(doc, dict):
        raise ValueError("GLB has no JSON chunk")
    return doc, binary


def _buffer_view_bytes(doc: dict[str, Any], binary: bytes, index: int) -> tuple[bytes, int | None]:
    view = doc["bufferViews"][index]
    if view.get("buffer", 0) != 0:
        raise ValueError("GLB: only the file's own buffer (0) is supported")
    start = view.get("byteOffset", 0)
    return binary[start: start + view["byteLength"]], view.get("byteStride")


def _read_accessor(doc: dict[str, Any], binary: bytes, index: int) -> NDArray[Any]:
    accessor = doc["accessors"][index]
    dtype = np.dtype(DTYPES[accessor["componentType"]])
    components = COMPONENTS[accessor["type"]]
    count = accessor["count"]
    if "bufferView" not in accessor:
        raise ValueError(f"GLB: accessor {index} has no bufferView (sparse/empty unsupported)")
    view, stride = _buffer_view_bytes(doc, binary, accessor["bufferView"])
    element = dtype.itemsize * components
    stride = stride or element
    start = accessor.get("byteOffset", 0)
    raw = np.frombuffer(view, dtype=np.uint8)
    if start + stride * (count - 1) + element > len(raw):
        raise ValueError(f"GLB: accessor {index} runs past its bufferView")
    rows = np.lib.stride_tricks.as_strided(raw[start:], shape=(count, element),
                                           strides=(stride, 1))
    return np.ascontiguousarray(rows).view(dtype).reshape(count, components)


def _to_uint8_colors(values: NDArray[Any], accessor: dict[str, Any]) -> NDArray[np.uint8]:
    rgb = values[:, :3]
    if rgb.dtype == np.uint8:
        return np.asarray(rgb, dtype=np.uint8)
    if rgb.dtype == np.uint16:
        return np.rint(rgb / 257.0).astype(np.uint8)
    if accessor.get("normalized", False) or rgb.dtype == np.float32:
        return np.clip(np.rint(rgb.astype(np.float64) * 255.0), 0, 255).astype(np.uint8)
    raise ValueError(f"GLB: unsupported COLOR_0 component type {accessor['componentType']}")


def _read_primitive(doc: dict[str, Any], binary: bytes, prim: dict[str, Any]) -> TriangleMesh:
    attributes = prim.get("attributes", {})
    if "POSITION" not in attributes:
        raise ValueError("GLB: a primitive has no POSITION")
    draco = prim.get("extensions", {}).get(DRACO_EXTENSION)
    if draco is not None:
        view, _ = _buffer_view_bytes(doc, binary, draco["bufferView"])
        try:
            decoded = DracoPy.decode(view)
        except Exception as exc:  # DracoPy raises its own failure types
            raise ValueError(f"GLB: Draco data cannot be decoded ({exc})") from None

        def attribute(name: str) -> NDArray[Any] | None:
            if name not in draco["attributes"]:
                return None
            found = decoded.get_attribute_by_unique_id(draco["attributes"][name])
            return None if found is None else np.asarray(found["data"])

        positions = np.asarray(decoded.points)
        faces = np.asarray(decoded.faces).reshape(-1, 3)
        normals, colors = attribute("NORMAL"), attribute("COLOR_0")
    else:
        positions = _read_accessor(doc, binary, attributes["POSITION"])
        if "indices" in prim:
            faces = _read_accessor(doc, binary, prim["indices"]).reshape(-1, 3)
        else:
            faces = np.arange(len(positions)).reshape(-1, 3)
        normals = (_read_accessor(doc, binary, attributes["NORMAL"])
                   if "NORMAL" in attributes else None)
        colors = (_read_accessor(doc, binary, attributes["COLOR_0"])
                  if "COLOR_0" in attributes else None)
    if colors is not None:
        colors = _to_uint8_colors(colors, doc["accessors"][attributes["COLOR_0"]])
    return TriangleMesh(
        vertices_m=np.asarray(positions, dtype=np.float64),
        faces=np.asarray(faces, dtype=np.int32),
        vertex_colors=colors,
        vertex_normals=None if normals is None else np.asarray(normals, dtype=np.float32),
    )


def _concatenate(parts: list[TriangleMesh]) -> TriangleMesh:
    if len(parts) == 1:
        return parts[0]
    offsets = np.cumsum([0] + [p.vertex_count for p in parts[:-1]])
    keep_colors = all(p.vertex_colors is not None for p in parts)
    keep_normals = all(p.vertex_normals is not None for p in parts)
    return TriangleMesh(
        vertices_m=np.concatenate([p.vertices_m for p in parts]),
        faces=np.concatenate([p.faces + o for p, o in zip(parts, offsets, strict=True)]).astype(
            np.int32),
        vertex_colors=(np.concatenate([p.vertex_colors for p in parts])  # type: ignore[misc]
                       if keep_colors else None),
        vertex_normals=(np.concatenate([p.vertex_normals for p in parts])  # type: ignore[misc]
                        if keep_normals else None),
    )
