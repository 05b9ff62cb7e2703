"""Reading the stage lines of worker and gateway logs: which stages of a job started, stored
their output, or were queued again after their worker died."""

from __future__ import annotations

import re
from typing import Any


def requeued(log_text: str, job_id: str) -> list[tuple[int, str]]:
    """The (index, name) of each stage of the job that a gateway queued again."""
    pattern = rf"job {job_id} stage (\d+) \((\w+)\): its worker stopped answering"
    return [(int(i), name) for i, name in re.findall(pattern, log_text)]


def stage_lines(log_text: str, job_id: str, what: str) -> dict[int, int]:
    """How many times each stage of the job logged ``what`` ("starting", "stored output")."""
    counts: dict[int, int] = {}
    for index in re.findall(rf"job {job_id} stage (\d+) \(\w+\) {what}", log_text):
        counts[int(index)] = counts.get(int(index), 0) + 1
    return counts


def check_stages_ran_once(log_text: str, job: dict[str, Any], killed: int) -> None:
    """Each stage started once (the killed one twice) and each work stage stored its output
    once: nothing finished before the kill was computed again, nothing ran twice at once."""
    stages = job["stages"]
    started = stage_lines(log_text, job["id"], "starting")
    assert started == {i: 2 if i == killed else 1 for i in range(len(stages))}, started
    stored = stage_lines(log_text, job["id"], "stored output")
    assert stored == {i: 1 for i in range(len(stages) - 1)}, stored  # export stores an asset
