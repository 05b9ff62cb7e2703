"""Frame-sets across devices: matched by timestamp within the sync window, every frame once."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from pipeline.io.k4a_sync import match_frames

PERIOD_US = 33_333
WINDOW_US = PERIOD_US // 2


@st.composite
def rigs(draw: st.DrawFn) -> list[dict[int, int]]:
    """Per device, frame number -> timestamp: a device offset and per-frame jitter that keep one
    instant's frames within 10 ms, starts and ends that differ, and dropped frames between."""
    devices = draw(st.integers(1, 5))
    rig = []
    for _ in range(devices):
        first = draw(st.integers(0, 3))
        last = draw(st.integers(first, 14))
        offset = draw(st.integers(0, 6_000))
        inside = list(range(first + 1, last))
        drops = draw(st.sets(st.sampled_from(inside), max_size=len(inside) // 2)
                     if inside else st.just(set()))
        rig.append({k: 1_000_000 + k * PERIOD_US + offset + draw(st.integers(-2_000, 2_000))
                    for k in range(first, last + 1) if k not in drops})
    return rig


@given(rigs())
def test_frame_sets_gather_one_instant_and_account_for_every_frame(
        rig: list[dict[int, int]]) -> None:
    streams = [iter([(k, t) for k, t in sorted(frames.items())]) for frames in rig]
    sets = list(match_frames(streams, lambda frame: frame[1], WINDOW_US))

    instants = sorted(set().union(*rig))
    assert len(sets) == len(instants)
    for instant, frame_set in zip(instants, sets, strict=True):
        members = [f for f in frame_set.frames if f is not None]
        assert {k for k, _ in members} == {instant}  # one instant per set
        assert frame_set.timestamp_us == min(t for _, t in members)
        expected_slots = [instant in frames for frames in rig]
        assert [f is not None for f in frame_set.frames] == expected_slots
        assert frame_set.complete == all(expected_slots)
        # missing while recording (between its first and last frame) is a dropped frame
        assert frame_set.dropped == tuple(
            d for d, frames in enumerate(rig)
            if instant not in frames and min(frames) < instant < max(frames))


def test_a_set_needs_every_frame_within_the_window() -> None:
    a = iter([100, 200])
    b = iter([100 + 50, 200 + 51])
    sets = list(match_frames([a, b], lambda t: t, 50))
    assert [s.complete for s in sets] == [True, False, False]
    assert sets[1].frames == (200, None) and sets[2].frames == (None, 251)


def test_a_negative_window_is_refused() -> None:
    with pytest.raises(ValueError, match="sync window"):
        list(match_frames([iter([1])], lambda t: t, -1))
