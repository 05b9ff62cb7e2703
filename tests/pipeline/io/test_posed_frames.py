from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from pipeline.capture import Intrinsics
from pipeline.io.capture_io import open_capture
from pipeline.io.posed_frames import (
    ROOM_INTRINSICS,
    UP_FROM_OPTICAL,
    pose_from_line,
    read_pgm_u16,
    read_posed_frames,
    write_posed_frames_capture,
)
from pipeline.reconstruct.registration import camera_points_image, invert_rigid, ray_image

ROOM = Path(__file__).resolve().parents[4] / "shared" / "data" / "real" / "kinect-room-5-frames"
TINY = Intrinsics(width=8, height=6, fx=10.0, fy=11.0, cx=3.5, cy=2.5)


@settings(max_examples=30, deadline=None)
@given(quat=st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(
    lambda q: np.linalg.norm(q) > 0.6), shift=st.lists(st.floats(-5, 5), min_size=3, max_size=3))
def test_a_pose_line_is_translation_then_quaternion_xyzw(quat: list[float],
                                                          shift: list[float]) -> None:
    line = " ".join(f"{v!r}" for v in [*shift, *quat])
    pose = pose_from_line(line, "pose.txt:1")
    np.testing.assert_allclose(pose[:3, :3], Rotation.from_quat(quat).as_matrix(), atol=1e-9)
    np.testing.assert_allclose(pose[:3, 3], shift)
    np.testing.assert_array_equal(pose[3], [0, 0, 0, 1])


@pytest.mark.parametrize("line", ["1 2 3 0 0 0", "1 2 3 0 0 0 x", "0 0 0 0 0 0 0",
                                  "1 2 nan 0 0 0 1"])
def test_a_bad_pose_line_is_named(line: str) -> None:
    with pytest.raises(ValueError, match=r"pose\.txt:4"):
        pose_from_line(line, "pose.txt:4")


def _write_pgm(path: Path, image: np.ndarray, maxval: int = 65535, comment: bool = True) -> None:
    height, width = image.shape
    header = b"P5\n" + (b"# written by a test\n" if comment else b"")
    header += f"{width} {height}\n{maxval}\n".encode()
    path.write_bytes(header + image.astype(">u2").tobytes())


def test_a_16_bit_pgm_is_read_big_endian(tmp_path: Path) -> None:
    image = np.arange(48, dtype=np.uint16).reshape(6, 8) * 1021
    _write_pgm(tmp_path / "d.pgm", image)
    np.testing.assert_array_equal(read_pgm_u16(tmp_path / "d.pgm"), image)


def test_a_pgm_that_is_not_16_bit_or_is_short_is_refused(tmp_path: Path) -> None:
    image = np.ones((6, 8), dtype=np.uint16)
    _write_pgm(tmp_path / "a.pgm", image, maxval=255)
    with pytest.raises(ValueError, match="maxval"):
        read_pgm_u16(tmp_path / "a.pgm")
    _write_pgm(tmp_path / "b.pgm", image)
    (tmp_path / "b.pgm").write_bytes((tmp_path / "b.pgm").read_bytes()[:-3])
    with pytest.raises(ValueError, match="bytes of samples"):
        read_pgm_u16(tmp_path / "b.pgm")
    (tmp_path / "c.pgm").write_bytes(b"P2\n8 6\n65535\n")
    with pytest.raises(ValueError, match="P5"):
        read_pgm_u16(tmp_path / "c.pgm")


def _tiny_folder(root: Path) -> list[np.ndarray]:
    (root / "depth").mkdir(parents=True)
    (root / "color").mkdir()
    poses = ["0 0 0 0 0 0 1", "0.5 -0.1 0.2 0 0.0998 0 0.995"]
    (root / "pose.txt").write_text("\n".join(poses) + "\n")
    depths = []
    for n in (1, 2):
        depth = (np.arange(48, dtype=np.uint16).reshape(6, 8) * 10 + 1000 * n)
        depth[0, 0] = 0
        _write_pgm(root / "depth" / f"{n}.pgm", depth)
        color = np.zeros((6, 8, 3), np.uint8)
        color[..., 2] = 200  # red, in OpenCV's BGR order
        cv2.imwrite(str(root / "color" / f"{n}.png"), color)
        depths.append(depth)
    return depths


def test_each_frame_becomes_a_posed_camera(tmp_path: Path) -> None:
    depths = _tiny_folder(tmp_path / "room")
    meta, views = read_posed_frames(tmp_path / "room", TINY)
    assert meta.camera_ids == ("frame1", "frame2") and meta.frame_indices == (0,)
    second = pose_from_line("0.5 -0.1 0.2 0 0.0998 0 0.995", "")
    assert meta.cameras[1].world_from_depth is not None
    np.testing.assert_allclose(meta.cameras[1].world_from_depth, UP_FROM_OPTICAL @ second)
    assert meta.cameras[0].color_intrinsics is None and meta.depth_scale == 0.001
    np.testing.assert_allclose(views[1].depth_m, depths[1] / 1000.0, rtol=1e-6)
    assert views[0].color_rgb is not None and views[0].color_rgb[0, 0].tolist() == [200, 0, 0]
    # +Y is up in the capture: the optical y axis (down) points down the world's y.
    assert meta.cameras[0].world_from_depth is not None
    assert meta.cameras[0].world_from_depth[1, 1] == -1.0


def test_the_capture_written_reads_back(tmp_path: Path) -> None:
    depths = _tiny_folder(tmp_path / "room")
    written = write_posed_frames_capture(tmp_path / "room", tmp_path / "capture", TINY)
    with open_capture(tmp_path / "capture") as reader:
        assert reader.meta.camera_ids == written.camera_ids
        view = reader.read_view("frame2", 0)
        np.testing.assert_allclose(view.depth_m, depths[1] / 1000.0, rtol=1e-6)
        assert view.color_rgb is not None and view.color_rgb.shape == (6, 8, 3)


def test_a_stride_keeps_the_same_rays(tmp_path: Path) -> None:
    _tiny_folder(tmp_path / "room")
    _, full = read_posed_frames(tmp_path / "room", TINY)
    meta, half = read_posed_frames(tmp_path / "room", TINY, stride=2)
    model = meta.cameras[0].depth_intrinsics
    assert (model.width, model.height) == (4, 3) == half[0].depth_m.shape[::-1]
    np.testing.assert_allclose(ray_image(model), ray_image(TINY)[::2, ::2], atol=1e-6)
    np.testing.assert_array_equal(half[1].depth_m, full[1].depth_m[::2, ::2])


def test_a_missing_depth_image_is_named(tmp_path: Path) -> None:
    _tiny_folder(tmp_path / "room")
    (tmp_path / "room" / "depth" / "2.pgm").unlink()
    with pytest.raises(ValueError, match="2.pgm"):
        read_posed_frames(tmp_path / "room", TINY)


def _near_share(ref: tuple[np.ndarray, np.ndarray], other: tuple[np.ndarray, np.ndarray],
                ref_pose: np.ndarray, other_pose: np.ndarray) -> float:
    """Share of the other frame's points (0.5-4 m) within 3 cm of the reference frame's."""
    def cloud(view: tuple[np.ndarray, np.ndarray], pose: np.ndarray) -> np.ndarray:
        rays, depth = view
        ok = (depth > 0.5) & (depth < 4.0)
        pts = camera_points_image(depth, rays)[ok].astype(np.float64)
        return pts @ pose[:3, :3].T + pose[:3, 3]

    dist, _ = cKDTree(cloud(ref, ref_pose)).query(cloud(other, other_pose), workers=2)
    return float(np.mean(dist < 0.03))


@pytest.mark.skipif(not (ROOM / "pose.txt").is_file(), reason="shared real data absent")
def test_the_room_poses_are_camera_to_world() -> None:
    """Back-projected with pose.txt read as camera-to-world, neighbouring frames overlap;
    read the other way round, they do not."""
    meta, views = read_posed_frames(ROOM, ROOM_INTRINSICS, stride=2)
    rays = ray_image(meta.cameras[0].depth_intrinsics)
    poses = [np.asarray(c.world_from_depth) for c in meta.cameras]
    for a, b in ((2, 3), (3, 4)):
        first, second = (rays, views[a].depth_m), (rays, views[b].depth_m)
        assert _near_share(first, second, poses[a], poses[b]) > 0.6
        inverted = [UP_FROM_OPTICAL @ invert_rigid(UP_FROM_OPTICAL.T @ p) for p in poses]
        assert _near_share(first, second, inverted[a], inverted[b]) < 0.2
