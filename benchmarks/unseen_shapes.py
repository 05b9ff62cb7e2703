"""Writes shapes that no volumesh network was trained on, each in another mesh format, for
`enhance_meshes.py --meshes DIR` (the acceptance runs the protocol on meshes from outside
shared/; none can be downloaded here). Prints JSON: each file, its vertices, faces, whether it
is closed and its Euler characteristic.

    .venv/bin/python benchmarks/unseen_shapes.py --out DIR
    .venv/bin/python benchmarks/enhance_meshes.py --meshes DIR

- arrow.ply: a cylinder and a cone, axis upright: sharp rims, a point, flat discs;
- sphere-and-torus.off: two pieces, one of genus 1;
- thin-plate.stl: an upright plate 3 cm thick (1 m high after the protocol's scaling), thinner
  than twice the noise's ±1 cm, so the noisy sides cross;
- mobius.ply: a Möbius strip, one-sided with an open boundary.

The training set's procedural shapes (`pipeline.enhance.data.procedural_meshes`) are of the same
families as the first two (spheres, tori, boxes, cylinders, blobs), so these are unseen meshes
but not unseen kinds of surface; the protocol meshes in shared/ are the scans.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import open3d as o3d
import trimesh


def shapes() -> dict[str, o3d.geometry.TriangleMesh]:
    """The shapes by file name."""
    upright = o3d.geometry.get_rotation_matrix_from_xyz((-np.pi / 2, 0.0, 0.0))
    arrow = o3d.geometry.TriangleMesh.create_arrow(0.08, 0.15, 0.6, 0.3, 40, 8, 6)
    sphere = o3d.geometry.TriangleMesh.create_sphere(0.3, 40)
    torus = o3d.geometry.TriangleMesh.create_torus(0.35, 0.12, 60, 30).translate((0, 0.7, 0))
    return {
        "arrow.ply": arrow.rotate(upright, center=(0.0, 0.0, 0.0)),
        "sphere-and-torus.off": sphere + torus,
        "thin-plate.stl": o3d.geometry.TriangleMesh.create_box(0.6, 1.0, 0.03)
        .subdivide_midpoint(4),
        "mobius.ply": o3d.geometry.TriangleMesh.create_mobius(
            length_split=120, width_split=12, twists=1, radius=0.5, flatness=1, width=0.4),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", required=True, help="folder to write the shapes to")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    report = {}
    for name, shape in shapes().items():
        shape.remove_duplicated_vertices()
        mesh = trimesh.Trimesh(np.asarray(shape.vertices), np.asarray(shape.triangles))
        mesh.export(out / name)
        report[name] = {"vertices": len(mesh.vertices), "faces": len(mesh.faces),
                        "closed": bool(mesh.is_watertight), "euler": int(mesh.euler_number)}
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
