"""Sources: a capture replayed as stored, recordings matched as `import-mkv` matches them, the
synthetic rig frame-set by frame-set; each resumes at a position."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from agent.sources import SourceOptions, open_source
from pipeline.capture import CameraInfo, CaptureMeta, FrameInfo, Intrinsics
from pipeline.io.capture_io import StoredFiles, StoredView, write_capture, zip_capture
from tests.k4a_recordings import DEPTH_SIZES, RecordingSpec, depth_image_mm, write_recording

SMALL = Intrinsics(width=32, height=24, fx=30.0, fy=30.0, cx=15.5, cy=11.5)


def _decoded(data: bytes) -> np.ndarray:
    import cv2

    return np.asarray(cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED))


def _capture(folder: Path, timestamps_us: list[int]) -> tuple[Path, list[list[StoredView]]]:
    import cv2

    cameras = (CameraInfo("left", SMALL), CameraInfo("right", SMALL))
    frames = tuple(FrameInfo(i, t) for i, t in enumerate(timestamps_us))
    rng = np.random.default_rng(0)
    views = []
    for frame in frames:
        rgb = rng.integers(0, 255, (24, 32, 3), dtype=np.uint8)
        ok, jpeg = cv2.imencode(".jpg", rgb)
        assert ok
        views.append([
            StoredView(cameras[0], frame.index,
                       rng.integers(0, 9000, (24, 32), dtype=np.uint16), color_rgb=rgb),
            StoredView(cameras[1], frame.index,
                       rng.integers(0, 9000, (24, 32), dtype=np.uint16),
                       color_jpeg=jpeg.tobytes())])
    out = folder / "capture"
    write_capture(out, CaptureMeta(0.0005, cameras, frames), [v for f in views for v in f])
    return out, views


@pytest.mark.parametrize("packed", [False, True])
def test_a_capture_replays_as_stored_and_resumes_at_a_position(tmp_path: Path,
                                                                 packed: bool) -> None:
    folder, stored = _capture(tmp_path, [1000, 67_667, 134_333, 201_000])
    if packed:
        zip_capture(folder, tmp_path / "capture.zip")
        folder = tmp_path / "capture.zip"
    source = open_source(f"capture:{folder}")
    try:
        assert source.info.live is False and source.info.depth_scale == 0.0005
        assert [c.id for c in source.info.cameras] == ["left", "right"]
        assert source.info.fps == pytest.approx(15.0, rel=0.01)  # from the timestamps
        sets = list(source.frame_sets(0))
        assert [(s.position, s.timestamp_us) for s in sets] == \
            [(0, 1000), (1, 67_667), (2, 134_333), (3, 201_000)]
        for frame_set, views in zip(sets, stored, strict=True):
            left, right = frame_set.views  # the files as stored, to pass on undecoded
            assert isinstance(left, StoredFiles) and isinstance(right, StoredFiles)
            np.testing.assert_array_equal(_decoded(left.depth_png), views[0].depth_units)
            assert left.color is not None and left.color_suffix == ".png"
            np.testing.assert_array_equal(_decoded(left.color)[:, :, ::-1], views[0].color_rgb)
            np.testing.assert_array_equal(_decoded(right.depth_png), views[1].depth_units)
            assert (right.color, right.color_suffix) == (views[1].color_jpeg, ".jpg")
        assert [s.position for s in source.frame_sets(2)] == [2, 3]
    finally:
        source.close()


def test_a_capture_without_timestamps_replays_at_the_given_rate(tmp_path: Path) -> None:
    folder, _ = _capture(tmp_path, [0, 0, 0])
    source = open_source(f"capture:{folder}", SourceOptions(fps=10.0))
    assert source.info.fps == 10.0
    assert [s.timestamp_us for s in source.frame_sets(0)] == [0, 100_000, 200_000]
    source.close()


def test_recordings_replay_their_complete_frame_sets_and_resume(tmp_path: Path) -> None:
    common = dict(depth_mode="NFOV_2X2BINNED", frame_count=6)
    paths = [write_recording(tmp_path / "a.mkv", RecordingSpec(**common, serial="1")),
             write_recording(tmp_path / "b.mkv", RecordingSpec(
                 **common, serial="2", color="BGRA", seed=1, dropped_depth=frozenset({2})))]
    source = open_source(f"mkv:{paths[0]},{paths[1]}")
    assert [c.id for c in source.info.cameras] == ["1", "2"]
    assert (source.info.fps, source.info.depth_scale, source.info.live) == (30.0, 0.001, False)
    sets = list(source.frame_sets(0))
    assert [s.position for s in sets] == [0, 1, 3, 4, 5]  # b lost frame 2's depth
    assert np.diff([s.timestamp_us for s in sets]).min() > 0
    width, height = DEPTH_SIZES["NFOV_2X2BINNED"]
    for frame_set in sets:
        a, b = frame_set.views
        np.testing.assert_array_equal(a.depth_units,
                                      depth_image_mm(width, height, frame_set.position, 0))
        np.testing.assert_array_equal(b.depth_units,
                                      depth_image_mm(width, height, frame_set.position, 1))
        assert a.color_jpeg is not None and a.color_jpeg[:2] == b"\xff\xd8"  # MJPG as recorded
        assert b.color_rgb is not None and b.color_rgb.shape == (720, 1280, 3)  # BGRA decoded
    assert [s.position for s in source.frame_sets(3)] == [3, 4, 5]


def test_the_synthetic_rig_renders_a_moving_subject_frame_set_by_frame_set() -> None:
    source = open_source("synthetic", SourceOptions(frames=3, fps=10.0))
    assert len(source.info.cameras) == 8
    assert all(c.world_from_depth is not None for c in source.info.cameras)  # previews
    sets = list(source.frame_sets(0))
    assert [(s.position, s.timestamp_us) for s in sets] == [(0, 0), (1, 100_000),
                                                             (2, 200_000)]
    assert all(len(s.views) == 8 and s.views[0].color_rgb is not None for s in sets)
    # The subject turns 6 degrees and sways between frames: its silhouette moves.
    first, last = (s.views[0].depth_units > 0 for s in (sets[0], sets[2]))
    assert (first != last).sum() > 0.01 * first.size
    resumed = list(source.frame_sets(2))
    assert [s.position for s in resumed] == [2]
