"""Recordings to a capture in-process: the writer's threads, frame-sets, calibration targets."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from pipeline.io.k4a_import import (
    ImportConfig,
    import_recordings,
    iter_frame_sets,
    open_recordings,
    read_target,
)
from tests.k4a_recordings import RecordingSpec, write_recording


def _pair(folder: Path) -> list[Path]:
    common = dict(depth_mode="NFOV_2X2BINNED", frame_count=6)
    return [write_recording(folder / "a.mkv", RecordingSpec(**common, serial="1")),
            write_recording(folder / "b.mkv", RecordingSpec(
                **common, serial="2", color="BGRA", seed=1, dropped_depth=frozenset({2}),
                dropped_color=frozenset({4})))]


def _files(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def test_any_number_of_writer_threads_writes_the_same_capture(tmp_path: Path) -> None:
    paths = _pair(tmp_path)
    fractions: list[float] = []
    one = import_recordings(open_recordings(paths, ImportConfig(writer_threads=1)),
                            tmp_path / "one", progress=fractions.append)
    three = import_recordings(open_recordings(paths, ImportConfig(writer_threads=3)),
                              tmp_path / "three")
    assert one == three
    assert (one.frame_sets, one.dropped, one.dropped_by_camera, one.missing_color) == \
        (5, 1, {"1": 0, "2": 1}, 1)
    assert fractions == sorted(fractions) and fractions[-1] == 1.0
    assert _files(tmp_path / "one") == _files(tmp_path / "three")
    names = _files(tmp_path / "one")
    assert "1/color/000000.jpg" in names and "2/color/000000.png" in names  # BGRA: lossless
    assert "2/color/000003.png" not in names  # frame 4 of b lost its colour


def test_frame_sets_keep_the_incomplete_ones_for_readers_that_want_them(
        tmp_path: Path) -> None:
    sets = list(iter_frame_sets(open_recordings(_pair(tmp_path))))
    assert [s.complete for s in sets] == [True, True, False, True, True, True]
    assert sets[2].dropped == (1,) and sets[2].frames[1] is None


def test_a_target_file_is_checked_as_capture_json_checks_it(tmp_path: Path) -> None:
    board = {"dictionary": "DICT_5X5_100", "squares_x": 7, "squares_y": 5,
             "square_length_m": 0.08, "marker_length_m": 0.06}
    good = tmp_path / "board.json"
    good.write_text(json.dumps({"boards": [board]}))
    assert read_target(good).boards[0].squares_x == 7
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"boards": [board | {"marker_length_m": 0.09}]}))
    with pytest.raises(ValueError, match=r"^bad\.json: boards\[0\]\.marker_length_m: must be "):
        read_target(bad)
    bad.write_text("[1]")
    with pytest.raises(ValueError, match=r"^bad\.json: must be an object"):
        read_target(bad)
