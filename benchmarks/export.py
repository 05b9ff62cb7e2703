"""GLB export figures: size and encode/decode time, plain vs Draco, and Draco's position error.

Usage: .venv/bin/python benchmarks/export.py [--mesh PATH] [--repeat N]
Without --mesh it builds a bumpy, vertex-coloured torus of exactly 100,000 triangles.
Prints one JSON object.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.geometry.mesh import TriangleMesh, vertex_normals  # noqa: E402
from pipeline.io.gltf_io import DracoConfig, encode_glb  # noqa: E402
from pipeline.io.gltf_read import decode_glb  # noqa: E402
from pipeline.io.mesh_io import read_mesh  # noqa: E402


def bumpy_torus(rings: int = 250, segments: int = 200) -> TriangleMesh:
    """A closed torus grid (2 * rings * segments triangles) with bumps, about 0.5 m across."""
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, rings, endpoint=False),
                       np.linspace(0, 2 * np.pi, segments, endpoint=False), indexing="ij")
    tube = 0.08 * (1.0 + 0.15 * np.sin(7 * u) * np.cos(5 * v))
    ring = 0.18 + tube * np.cos(v)
    vertices = np.stack([ring * np.cos(u), tube * np.sin(v), ring * np.sin(u)], -1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(rings), np.arange(segments), indexing="ij")
    a = i * segments + j
    b = ((i + 1) % rings) * segments + j
    c = ((i + 1) % rings) * segments + (j + 1) % segments
    d = i * segments + (j + 1) % segments
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                            np.stack([a, c, d], -1).reshape(-1, 3)]).astype(np.int32)
    return with_colors(TriangleMesh(vertices, faces))


def with_colors(mesh: TriangleMesh) -> TriangleMesh:
    """Colours by position (a smooth field, like a scan's), and normals computed once."""
    low, span = mesh.vertices_m.min(axis=0), np.ptp(mesh.vertices_m, axis=0).max()
    colors = np.clip(np.rint(255 * (mesh.vertices_m - low) / span), 0, 255).astype(np.uint8)
    return TriangleMesh(mesh.vertices_m, mesh.faces, colors,
                        vertex_normals(mesh.vertices_m, mesh.faces))


def best_time(function: Callable[[], Any], repeat: int) -> tuple[float, Any]:
    best, result = float("inf"), None
    for _ in range(repeat):
        start = time.perf_counter()
        result = function()
        best = min(best, time.perf_counter() - start)
    return best, result


def measure(mesh: TriangleMesh, draco: DracoConfig | None, repeat: int) -> dict[str, Any]:
    encode_s, data = best_time(lambda: encode_glb(mesh, draco=draco), repeat)
    decode_s, decoded = best_time(lambda: decode_glb(data), repeat)
    diagonal = float(np.linalg.norm(np.ptp(mesh.vertices_m, axis=0)))
    _, index = cKDTree(mesh.vertices_m).query(decoded.vertices_m)
    error = np.linalg.norm(decoded.vertices_m - mesh.vertices_m[index], axis=1)
    assert mesh.vertex_normals is not None and mesh.vertex_colors is not None
    cosine = np.sum(decoded.vertex_normals * mesh.vertex_normals[index], axis=1)
    return {
        "bytes": len(data),
        "encode_ms": round(1000 * encode_s, 1),
        "decode_ms": round(1000 * decode_s, 1),
        "max_position_error_rel_diagonal": float(error.max() / diagonal),
        "max_position_error_m": float(error.max()),
        "max_normal_error_deg": float(np.degrees(np.arccos(np.clip(cosine.min(), -1, 1)))),
        "colors_exact": bool(np.array_equal(decoded.vertex_colors, mesh.vertex_colors[index])),
        "faces": decoded.face_count,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mesh", type=Path, help="a mesh file (default: a 100k-triangle torus)")
    parser.add_argument("--repeat", type=int, default=3, help="runs per figure; the best counts")
    args = parser.parse_args()
    mesh = with_colors(read_mesh(args.mesh)) if args.mesh else bumpy_torus()
    variants: dict[str, DracoConfig | None] = {
        "plain": None,
        "draco_q11": DracoConfig(position_quantization_bits=11),
        "draco_q14": DracoConfig(position_quantization_bits=14),
    }
    results = {name: measure(mesh, config, args.repeat) for name, config in variants.items()}
    plain_bytes = results["plain"]["bytes"]
    for name in ("draco_q11", "draco_q14"):
        results[name]["ratio_to_plain"] = round(plain_bytes / results[name]["bytes"], 1)
    print(json.dumps({
        "mesh": str(args.mesh) if args.mesh else "bumpy torus",
        "vertices": mesh.vertex_count,
        "triangles": mesh.face_count,
        "draco_settings": "normals 10 bits, colours 8 bits, compression level 7",
        "machine": platform.processor() or platform.machine(),
        "results": results,
    }, indent=2))


if __name__ == "__main__":
    main()
