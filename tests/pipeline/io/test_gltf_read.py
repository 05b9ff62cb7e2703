"""GLB files written by other tools: interleaved buffers, 16-bit colours, unindexed and several
primitives read back as one mesh; broken files are refused naming the GLB."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from pipeline.geometry.mesh import TriangleMesh
from pipeline.io.glb_format import CHUNK_BIN, CHUNK_JSON, FLOAT, GLB_MAGIC, UINT, USHORT
from pipeline.io.gltf_io import encode_glb
from pipeline.io.gltf_read import decode_glb

TRIANGLE_M = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=np.float32)


def _glb(doc: dict, binary: bytes) -> bytes:
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    binary += b"\0" * (-len(binary) % 4)
    total = 12 + 8 + len(text) + 8 + len(binary)
    return (struct.pack("<III", GLB_MAGIC, 2, total) + struct.pack("<II", len(text), CHUNK_JSON)
            + text + struct.pack("<II", len(binary), CHUNK_BIN) + binary)


def _interleaved_triangle(colors_u16: np.ndarray) -> bytes:
    """One unindexed triangle whose positions and 16-bit colours share a strided view."""
    rows = [p.tobytes() + c.tobytes() for p, c in zip(TRIANGLE_M, colors_u16, strict=True)]
    binary = b"".join(rows)  # 12 + 8 bytes per vertex
    doc = {
        "asset": {"version": "2.0"},
        "buffers": [{"byteLength": len(binary)}],
        "bufferViews": [{"buffer": 0, "byteLength": len(binary), "byteStride": 20}],
        "accessors": [
            {"bufferView": 0, "componentType": FLOAT, "count": 3, "type": "VEC3"},
            {"bufferView": 0, "byteOffset": 12, "componentType": USHORT, "normalized": True,
             "count": 3, "type": "VEC4"},
        ],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "COLOR_0": 1}}]}],
    }
    return _glb(doc, binary)


def test_an_interleaved_unindexed_triangle_with_16_bit_colours_reads_back() -> None:
    colors = np.array([[65535, 0, 0, 65535], [0, 65535, 0, 65535], [0, 0, 257 * 128, 65535]],
                      dtype=np.uint16)
    mesh = decode_glb(_interleaved_triangle(colors))
    np.testing.assert_array_equal(mesh.vertices_m, TRIANGLE_M)
    np.testing.assert_array_equal(mesh.faces, [[0, 1, 2]])
    np.testing.assert_array_equal(mesh.vertex_colors, [[255, 0, 0], [0, 255, 0], [0, 0, 128]])
    assert mesh.vertex_normals is None


def test_several_primitives_become_one_mesh_with_offset_indices() -> None:
    indices = np.array([0, 1, 2], dtype=np.uint32)
    binary = TRIANGLE_M.tobytes() + (TRIANGLE_M + 5).tobytes() + indices.tobytes()
    doc = {
        "asset": {"version": "2.0"},
        "buffers": [{"byteLength": len(binary)}],
        "bufferViews": [{"buffer": 0, "byteOffset": 36 * k, "byteLength": 36} for k in range(2)]
        + [{"buffer": 0, "byteOffset": 72, "byteLength": 12}],
        "accessors": [{"bufferView": k, "componentType": FLOAT, "count": 3, "type": "VEC3"}
                      for k in range(2)]
        + [{"bufferView": 2, "componentType": UINT, "count": 3, "type": "SCALAR"}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 2}]},
                   {"primitives": [{"attributes": {"POSITION": 1}, "indices": 2},
                                   {"attributes": {"POSITION": 1}, "mode": 1}]}],  # lines: skipped
    }
    mesh = decode_glb(_glb(doc, binary))
    np.testing.assert_array_equal(mesh.vertices_m, np.vstack([TRIANGLE_M, TRIANGLE_M + 5]))
    np.testing.assert_array_equal(mesh.faces, [[0, 1, 2], [3, 4, 5]])


def test_broken_files_are_refused_naming_the_glb() -> None:
    good = encode_glb(TriangleMesh(TRIANGLE_M.astype(np.float64), np.array([[0, 1, 2]])))
    for data in (b"", b"not a glb at all, clearly", good[:100]):
        with pytest.raises(ValueError, match="GLB"):
            decode_glb(data)
    doc = {"asset": {"version": "2.0"}, "meshes": [{"primitives": [{"attributes": {}}]}]}
    with pytest.raises(ValueError, match="GLB: a primitive has no POSITION"):
        decode_glb(_glb(doc, b""))
    doc = {"asset": {"version": "2.0"}, "bufferViews": [{"buffer": 0, "byteLength": 12}],
           "accessors": [{"bufferView": 0, "componentType": FLOAT, "count": 3, "type": "VEC3"}],
           "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}]}
    with pytest.raises(ValueError, match="runs past its bufferView"):
        decode_glb(_glb(doc, bytes(12)))
