"""A folder of posed RGB-D frames (one moving sensor) as a multi-camera capture (format v1).

The folder holds ``depth/N.pgm`` (16-bit big-endian PGM, millimetres, 0 = no measurement),
``color/N.png`` (pixel-aligned with the depth of the same N) and ``pose.txt`` whose line N is
``tx ty tz qx qy qz qw``: the camera-to-world pose of frame N in metres (the layout of
slambook2's ``ch5/rgbd``, ../shared/data/real/kinect-room-5-frames). A static scene seen from
several poses is a multi-view input like a rig's, so each frame becomes a camera ``frameN``
of one capture frame.

The source world is that of the first camera's optical frame (OpenCV: y down, z forward); a
capture's world is +Y up (docs/capture-format.md), so poses are turned half a turn about x.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from pipeline.capture import CameraInfo, CaptureMeta, FrameInfo, Intrinsics, View
from pipeline.io.capture_io import write_capture

FloatArray = NDArray[np.float64]

ROOM_INTRINSICS = Intrinsics(width=640, height=480, fx=518.0, fy=519.0, cx=325.5, cy=253.5)
"""The Kinect's depth (and aligned colour) model in slambook2's ch5 code."""
DEPTH_SCALE_M = 0.001
"""The PGMs' unit: millimetres."""
UP_FROM_OPTICAL = np.diag([1.0, -1.0, -1.0, 1.0])
"""Half a turn about x: an OpenCV optical frame (y down) to a +Y-up world."""
_PGM_MAXVAL = 65535


def pose_from_line(line: str, where: str) -> FloatArray:
    """4x4 rigid transform of ``tx ty tz qx qy qz qw`` (the quaternion normalised)."""
    try:
        values = [float(v) for v in line.split()]
    except ValueError:
        raise ValueError(f"{where}: expected 7 numbers, got {line.strip()!r}") from None
    if len(values) != 7 or not np.all(np.isfinite(values)):
        raise ValueError(f"{where}: expected 7 finite numbers, got {line.strip()!r}")
    quat_xyzw = np.array(values[3:])
    norm = float(np.linalg.norm(quat_xyzw))
    if not norm > 0.5:
        raise ValueError(f"{where}: the quaternion is not a rotation (norm {norm:.3g})")
    x, y, z, w = quat_xyzw / norm
    pose = np.eye(4)
    pose[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                    [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                    [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    pose[:3, 3] = values[:3]
    return pose


def read_poses(path: Path) -> list[FloatArray]:
    """Camera-to-world poses, one per non-empty line of ``pose.txt``."""
    if not path.is_file():
        raise ValueError(f"{path}: not found")
    lines = [line for line in path.read_text().splitlines() if line.strip()]
    if not lines:
        raise ValueError(f"{path}: holds no pose")
    return [pose_from_line(line, f"{path}:{n}") for n, line in enumerate(lines, start=1)]


def read_pgm_u16(path: Path) -> NDArray[np.uint16]:
    """A binary 16-bit PGM (P5, maxval 65535, big-endian samples) as (H, W) uint16."""
    data = path.read_bytes()
    fields: list[bytes] = []
    position = 0
    while len(fields) < 4:
        while position < len(data) and data[position:position + 1].isspace():
            position += 1
        if data[position:position + 1] == b"#":  # a comment runs to the end of its line
            position = data.find(b"\n", position) + 1 or len(data)
            continue
        end = position
        while end < len(data) and not data[end:end + 1].isspace():
            end += 1
        if end == position:
            raise ValueError(f"{path}: truncated PGM header")
        fields.append(data[position:end])
        position = end
    if fields[0] != b"P5" or not all(f.isdigit() for f in fields[1:]):
        raise ValueError(f"{path}: not a binary PGM (P5) header")
    width, height, maxval = (int(f) for f in fields[1:])
    if maxval != _PGM_MAXVAL:
        raise ValueError(f"{path}: expected 16-bit samples (maxval 65535), got maxval {maxval}")
    pixels = data[position + 1:]  # one whitespace byte ends the header
    if len(pixels) != width * height * 2:
        raise ValueError(f"{path}: expected {width * height * 2} bytes of samples, "
                         f"got {len(pixels)}")
    return np.frombuffer(pixels, dtype=">u2").reshape(height, width).astype(np.uint16)


def _read_color_rgb(path: Path, intrinsics: Intrinsics) -> NDArray[np.uint8] | None:
    if not path.is_file():
        return None
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None or bgr.shape[:2] != (intrinsics.height, intrinsics.width):
        raise ValueError(f"{path}: not a {intrinsics.width}x{intrinsics.height} colour image")
    return np.ascontiguousarray(bgr[:, :, ::-1])


def strided(intrinsics: Intrinsics, stride: int) -> Intrinsics:
    """The model of every ``stride``-th pixel (from pixel 0) of an image of ``intrinsics``."""
    return Intrinsics(width=-(-intrinsics.width // stride), height=-(-intrinsics.height // stride),
                      fx=intrinsics.fx / stride, fy=intrinsics.fy / stride,
                      cx=intrinsics.cx / stride, cy=intrinsics.cy / stride,
                      distortion=intrinsics.distortion)


def read_posed_frames(folder: str | Path, intrinsics: Intrinsics = ROOM_INTRINSICS,
                      stride: int = 1) -> tuple[CaptureMeta, list[View]]:
    """The folder as a capture: camera ``frameN`` per line N of pose.txt, one capture frame 0.

    Each camera's ``world_from_depth`` is its pose in a +Y-up world; colour is registered to
    depth (no colour intrinsics), as the source's colour is pixel-aligned. ``stride`` keeps
    every stride-th pixel in x and y (a smaller capture of the same rays, for quick checks).
    """
    if stride < 1:
        raise ValueError(f"stride: must be >= 1, got {stride}")
    root = Path(folder)
    model = strided(intrinsics, stride)
    poses = read_poses(root / "pose.txt")
    cameras, views = [], []
    for n, source_from_camera in enumerate(poses, start=1):
        depth_path = root / "depth" / f"{n}.pgm"
        if not depth_path.is_file():
            raise ValueError(f"{depth_path}: not found (pose.txt has {len(poses)} poses)")
        depth_mm = read_pgm_u16(depth_path)
        if depth_mm.shape != (intrinsics.height, intrinsics.width):
            raise ValueError(f"{depth_path}: {depth_mm.shape[1]}x{depth_mm.shape[0]}, expected "
                             f"{intrinsics.width}x{intrinsics.height}")
        camera = CameraInfo(id=f"frame{n}", depth_intrinsics=model,
                            world_from_depth=UP_FROM_OPTICAL @ source_from_camera)
        cameras.append(camera)
        color = _read_color_rgb(root / "color" / f"{n}.png", intrinsics)
        views.append(View(camera=camera, frame_index=0,
                          depth_m=(depth_mm[::stride, ::stride].astype(np.float64)
                                   * DEPTH_SCALE_M).astype(np.float32),
                          color_rgb=None if color is None else color[::stride, ::stride]))
    meta = CaptureMeta(depth_scale=DEPTH_SCALE_M, cameras=tuple(cameras),
                       frames=(FrameInfo(index=0, timestamp_us=0),))
    return meta, views


def write_posed_frames_capture(folder: str | Path, out_dir: str | Path,
                               intrinsics: Intrinsics = ROOM_INTRINSICS, stride: int = 1
                               ) -> CaptureMeta:
    """Writes the folder's frames as a capture directory (format v1); returns its meta."""
    meta, views = read_posed_frames(folder, intrinsics, stride)
    write_capture(out_dir, meta, views)
    return meta
