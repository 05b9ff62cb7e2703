"""The status line: rates over the interval between two snapshots, counts that matter."""

from __future__ import annotations

from agent.stats import Snapshot, Stats, status_line


def test_the_status_line_shows_rates_sizes_and_trouble() -> None:
    stats = Stats()
    before = stats.snapshot(10.0, 0, 0)
    stats.add(captured=60, captured_bytes=30_000_000, sent=58, sent_bytes=29_000_000)
    stats.set_connection("retrying (ConnectError)")
    now = stats.snapshot(12.0, 2, 1_000_000)
    assert status_line(before, now) == (
        "captured 60 (30.0/s, 15.0 MB/s)  sent 58 (29.0/s, 14.5 MB/s)  spool 2 (1.0 MB)  "
        "gateway: retrying (ConnectError)")
    stats.add(dropped=3, rejected=1)
    line = status_line(now, stats.snapshot(13.0, 0, 0))
    assert line.endswith("dropped 3  rejected 1") and "(0.0/s" in line


def test_a_snapshot_starts_at_zero_and_connecting() -> None:
    assert Stats().snapshot(1.0, 0, 0) == Snapshot(at_s=1.0)
    assert Snapshot(at_s=0.0).connection == "connecting"
