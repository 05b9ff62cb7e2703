"""A capture written by another tool, following only docs/capture-format.md, reconstructs too.

Nothing here goes through volumesh's own writer: capture.json is written by hand, depth with a
finer scale, lens distortion on the depth camera, colour in JPEG at twice the resolution from its
own camera (colour_from_depth offset as on a Kinect), odd camera ids, all zipped under one top
folder.
"""

from __future__ import annotations

import json
import subprocess
import sys
import zipfile
from pathlib import Path

import cv2
import numpy as np

from pipeline.io.gltf_read import decode_glb
from tests.pipeline.sphere_scene import distance_to_sphere, ring_cameras, sphere_depth

DEPTH_SCALE = 0.00025
COLOUR_RGB = (40, 170, 90)
COLOR_FROM_DEPTH = [[1, 0, 0, -0.032], [0, 1, 0, -0.002], [0, 0, 1, 0.004], [0, 0, 0, 1]]


def _intrinsics_json(width: int, height: int, f: float, distortion: list[float]) -> dict:
    return {"width": width, "height": height, "fx": f, "fy": f, "cx": (width - 1) / 2,
            "cy": (height - 1) / 2, "distortion": distortion}


def _write_foreign_capture(zip_path: Path) -> None:
    distortion = (0.15, -0.05, 0.001, -0.0005)
    cameras = ring_cameras(6, 256, 224, distortion=distortion)
    rng = np.random.default_rng(3)
    doc: dict = {"format": "volumesh.capture/1", "depth_scale": DEPTH_SCALE, "cameras": [],
                 "frames": [{"index": 0, "timestamp_us": 1_700_000}], "target": None}
    with zipfile.ZipFile(zip_path, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for i, cam in enumerate(cameras):
            cam_id = f"Kinect_{chr(65 + i)}-01"
            intr = cam.depth_intrinsics
            assert cam.world_from_depth is not None
            doc["cameras"].append({
                "id": cam_id,
                "depth_intrinsics": _intrinsics_json(intr.width, intr.height, intr.fx,
                                                     list(distortion)),
                "color_intrinsics": _intrinsics_json(2 * intr.width, 2 * intr.height,
                                                     2 * intr.fx, []),
                "color_from_depth": COLOR_FROM_DEPTH,
                "world_from_depth": cam.world_from_depth.tolist()})
            depth_m = sphere_depth(cam, noise_m=0.0005, rng=rng)
            units = np.rint(depth_m / DEPTH_SCALE).astype(np.uint16)
            archive.writestr(f"take/{cam_id}/depth/000000.png",
                             cv2.imencode(".png", units)[1].tobytes())
            colour = np.zeros((2 * intr.height, 2 * intr.width, 3), np.uint8)
            colour[:] = COLOUR_RGB[::-1]  # OpenCV writes BGR
            archive.writestr(f"take/{cam_id}/color/000000.jpg",
                             cv2.imencode(".jpg", colour, [cv2.IMWRITE_JPEG_QUALITY, 95])[1]
                             .tobytes())
        archive.writestr("take/capture.json", json.dumps(doc))


def test_a_foreign_capture_reconstructs(tmp_path: Path) -> None:
    capture = tmp_path / "foreign.zip"
    _write_foreign_capture(capture)
    out = tmp_path / "out.glb"
    result = subprocess.run([sys.executable, "-m", "app", "reconstruct", str(capture),
                             "--out", str(out)], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    mesh = decode_glb(out.read_bytes())
    distance = distance_to_sphere(mesh.vertices_m)
    assert mesh.face_count > 1000
    # A few tenths of a millimetre; with the distortion ignored it would be millimetres.
    assert np.sqrt(np.mean(distance**2)) < 0.0006
    assert mesh.vertex_colors is not None
    seen = np.abs(mesh.vertex_colors.astype(int) - COLOUR_RGB).max(axis=1) <= 6
    assert seen.mean() > 0.9
